// Controllers of the element tests that steer the cell every step (docs/loading-paths.md):
// "cyclic" (cyclic triaxial loading between two bounds of q or of the axial strain) and
// "true_triaxial" (the lateral stress targets that hold p and b while axis 3 is strained).
#pragma once
#include "qsdem/run/controller.hpp"

namespace qsdem {

// The deviator of the triaxial test, q = s33 - (s11 + s22)/2 (compression positive; SPEC 7's
// q = sqrt(3 J2) is its magnitude when s11 = s22 and the shear stresses vanish).
double axial_deviator(const Mat3& stress);

// One closed cycle of a cyclic phase (Cyclic in path_control.cpp): from a top corner through a
// bottom corner to the next top corner. q is axial_deviator, e1 the axial strain from the phase's
// start (compression positive), ev = V/V0 - 1.
struct CycleLoop {
  double q_max = 0, q_min = 0;    // q at the closing top corner and at the bottom corner (Pa)
  double e1_max = 0, e1_min = 0;  // e1 at them
  double work = 0;                // W_loop: the area of the q-e1 loop closed by its chord (J/m^3)
  double e1 = 0, ev = 0;          // e1 and ev at the closing corner (accumulated since the phase's start)
  // E_sec = (q_max - q_min) / (e1_max - e1_min)
  double secant_modulus() const { return (q_max - q_min) / (e1_max - e1_min); }
  // D = W_loop / (4 pi W_s), W_s = (1/2) (dq/2) (de1/2) (ASTM D3999-11 section 10.2; Kokusho 1980)
  double damping_ratio() const;
};

ControllerFactory read_cyclic(ControllerKeys& keys, const Phase& phase, double step_ratio);
ControllerFactory read_true_triaxial(ControllerKeys& keys, const Phase& phase, double step_ratio);

}  // namespace qsdem
