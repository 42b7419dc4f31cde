// The page of a `qsdem converge` certificate (DIR/certificate.html): the verdict and its reason,
// each rung's change against the slowest with its noise, the limits, the cost, and the ladder's
// figure; what certificate.json holds, for a reader.
#pragma once
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace qsdem {

// `certificate`: DIR/certificate.json's content; `figures`: the ladder figures' PNG names under
// DIR/analysis/figures/ (shown in this order).
std::string certificate_html(const nlohmann::ordered_json& certificate, const std::vector<std::string>& figures);

}  // namespace qsdem
