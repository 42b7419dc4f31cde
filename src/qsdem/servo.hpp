// Cell control (SPEC 3): each axis is fixed, strain-rate controlled or stress controlled.
#pragma once
#include "qsdem/model.hpp"
#include "qsdem/state.hpp"

namespace qsdem {

// Sets state.cell.L (diagonal) for the coming step from the stress at t.
//
// Strain-rate axis k: the engineering strain e = (H0 - H)/H0 grows at the given rate, so
//   L_kk = -rate H0 / H.
// Stress axis k (compression positive), a PI servo scaled by the affine stiffness C_kk
// (State::affine_stiffness, the stress change per unit affine strain of the contacts):
//   e_k = (sigma_target - sigma_kk) / sigma_target,   S_k += e_k,
//   L_kk = -(beta e_k + gamma S_k) sigma_target / (C_kk dt),   |L_kk| <= max rate.
// beta is the fraction of the stress error removed per step by the affine response (stable for
// beta < 1 since the true response is softer than the affine one); gamma removes the steady
// error a constant-rate ramp leaves. This is SPEC 3's L_kk = -g (sigma_t - sigma)/sigma_t with
// g = beta sigma_t / (C_kk dt), plus the integral term. Without contacts (C_kk = 0) the axis
// moves at the maximum rate. The integral does not accumulate while the rate is clamped.
void servo_update(const Model& model, State& state);

}  // namespace qsdem
