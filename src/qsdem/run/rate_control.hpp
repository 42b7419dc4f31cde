// "rate": a controller of a strain-rate component's eps' that holds an equilibrium index (UFR,
// Iuf or IMom) near a target (docs/physics.md, "Adaptive loading rate").
#pragma once
#include "qsdem/run/controller.hpp"

namespace qsdem {

struct RateControlSettings {
  enum class Index : std::int32_t { imom, ufr, iuf };
  int component = 2;            // the strain-rate normal component it drives
  Index index = Index::imom;
  double target = 0;            // the index's target (ratio)
  double min_rate = 0, max_rate = 0;  // bounds of |eps'|
  double max_factor = 2;        // |eps'| changes by at most this factor per sample point
  double gain = 0.2;            // the share of the full step taken at each sample point
  double exponent = 0.85;       // b of I ~ a eps'^b (paper Fig. 9)
  long filter_points = 4;       // k of the moving average of log I
  double band = 1.5;            // a row is within the band when target / band <= I <= target band
  double step_ratio = 0;        // c_t (time.step_ratio): the steps of a constant-rate run
};

// The index of m that `index` names.
double rate_control_index(const Measures& m, RateControlSettings::Index index);

// Reads the keys of a [phase.controller] table of kind "rate" ([triaxial.rate_control] is written
// as one, config.cpp).
ControllerFactory read_rate_control(ControllerKeys& keys, const Phase& phase, double step_ratio);

}  // namespace qsdem
