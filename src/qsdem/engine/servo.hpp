// Cell control (SPEC 3): each component of L is fixed, strain-rate controlled or stress controlled.
#pragma once
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/state.hpp"

namespace qsdem {

// Sets state.cell.L for the coming step from the stress at t.
//
// Strain-rate axis k: the engineering strain e = (H0 - H)/H0 grows at the given rate, so
//   L_kk = -rate H0 / H,
// with H = h_kk: a diagonal L scales row k of h by (1 + dt L_kk), so h_kk measures the axis
// exactly even when the cell carries a small tilt (the shear servo below).
// Stress axis k (compression positive), a PI servo scaled by the affine stiffness C_kk
// (State::affine_stiffness, the stress change per unit affine strain of the contacts):
//   e_k = (sigma_target - sigma_kk) / sigma_target,   S_k += e_k,
//   L_kk = -(beta e_k + gamma S_k) sigma_target / (C_kk dt),   |L_kk| <= max rate.
// beta is the fraction of the stress error removed per step by the affine response (stable for
// beta < 1 since the true response is softer than the affine one); gamma removes the steady
// error a constant-rate ramp leaves. This is SPEC 3's L_kk = -g (sigma_t - sigma)/sigma_t with
// g = beta sigma_t / (C_kk dt), plus the integral term. Without contacts (C_kk = 0) the axis
// moves at the maximum rate. The integral does not accumulate while the rate is clamped.
// Contact dashpots (a law with has_dashpots) add a viscous stress -eta_kk L_kk, eta_kk
// (State::affine_viscosity) the same sum as C_kk with the viscous coefficients: the measured
// stress holds eta_kk times the last step's rate L'_kk, and the new rate's, so the rate that
// removes the same fraction of the error is
//   L_kk = (eta_kk L'_kk - (beta e_k + gamma S_k) sigma_target) / (C_kk dt + eta_kk),
// the form above for eta_kk = 0. (Left out, eta would make the loop gain beta eta / (C dt),
// ~2.6 on paper-A-small with e = 0.5: the rate would switch sign at the cap every step.)
//
// Shear component ab (12, 13, 23), strain-rate controlled: simple shear L_ab = rate (x_a moves in
// proportion to x_b; L_ba = 0).
// Shear component ab, stress controlled (a target, most often zero): SPEC 3 keeps L diagonal,
// so nothing would relax the shear stress a finite packing locks in while it jams (10-16 % of p
// measured at 200-8000 particles) or builds while it is sheared. A pure shear rate D_ab = D_ba
// drives sigma_ab to its target, proportionally:
//   L_ab = L_ba = (beta (sigma_ab - target) + eta_ab L'_ab) / (G_ab dt + eta_ab),   |L_ab| <= max rate,
// with G_ab (State::shear_stiffness) the affine stiffness -d sigma_ab / d(D_ab dt) of the contacts:
//   G_ab = (1/V) sum |l|^2 [2 k_n n_a^2 n_b^2 + k_t ((n_a^2 + n_b^2)/2 - 2 n_a^2 n_b^2)],
// and eta_ab (State::shear_viscosity) the same sum of the dashpots' coefficients (0 without).
// It acts only once every stress-controlled normal stress is within 10 % of its target: in the
// loose, collisional stage the shear stresses are noise, and chasing them would only tilt the
// cell. The strain it then takes is small, so the cell stays nearly orthorhombic.
//
// Constant-volume axes (an undrained test, SPEC 3.7): once every other component of L is set,
// the constant-volume normal components share one rate r, chosen so that the step's update
// h <- (I + dt L) h keeps det h: det(I + dt L) = 1 exactly, solved for x = 1 + dt r by Newton's
// method (a polynomial of degree 1 or 2 in x, from x = 1; converged to round-off in 2 to 3
// iterations). To first order r = -(sum of the other L_kk) / n (L11 = L22 = -L33/2 for axial
// loading); the rate form alone loses 3/4 (dt L33)^2 of the volume per step.
void servo_update(const Model& model, State& state);

}  // namespace qsdem
