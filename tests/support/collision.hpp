// A two-particle collision stepped to its end, as the contact-law, damping, energy and inertia tests
// drive it. Header-only, tests only.
#pragma once
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/engine/step.hpp"

namespace qsdem_test {

// Steps `st` until its first pair has touched and parted, at most `max_steps` steps; returns the
// steps in contact (overlap > 0), 0 when the pair never touched.
inline long step_through_collision(const qsdem::Model& m, qsdem::State& st, long max_steps) {
  long contact = 0;
  for (long k = 0; k < max_steps; ++k) {
    qsdem::step(m, st);
    const bool touching = st.pairs.size() > 0 && st.pairs.overlap[0] > 0;
    if (touching) ++contact;
    else if (contact > 0) break;
  }
  return contact;
}

}  // namespace qsdem_test
