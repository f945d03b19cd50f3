#pragma once
// Small in-memory scenes for the solver tests.

#include <string>

#include <nlohmann/json.hpp>

#include "mpm/scene.hpp"

namespace mpm::test {

/// One elastic box of `dim` dimensions in a grid box [0, 1]^dim with spacing h, no walls,
/// no gravity. Tests edit the JSON before parsing.
inline nlohmann::json box_scene(int dim, const std::string& shape, double h = 0.1) {
  nlohmann::json lo = nlohmann::json::array(), hi = nlohmann::json::array(),
                 zero = nlohmann::json::array(), one = nlohmann::json::array();
  for (int d = 0; d < dim; ++d) {
    lo.push_back(0.3);
    hi.push_back(0.7);
    zero.push_back(0.0);
    one.push_back(1.0);
  }
  return {
      {"dimension", dim},
      {"grid", {{"min", zero}, {"max", one}, {"spacing", h}}},
      {"shape_function", shape},
      {"scheme", {{"update", "musl"}, {"transfer", "apic"}, {"mass_threshold", 0.0}}},
      {"materials",
       {{{"name", "m"},
         {"model", "linear_elastic"},
         {"density", 1000.0},
         {"youngs_modulus", 1.0e6},
         {"poisson_ratio", 0.3}}}},
      {"bodies",
       {{{"name", "block"},
         {"material", "m"},
         {"shape", {{"type", "box"}, {"min", lo}, {"max", hi}}},
         {"particles_per_cell", 2}}}},
      {"time", {{"end", 1.0}}},
  };
}

inline Scene parse(const nlohmann::json& doc) { return parse_scene(doc, "<test>"); }

inline Scene load_data_scene(const std::string& name) {
  return load_scene(std::string(MPM_DATA_DIR) + "/scenes/" + name);
}

}  // namespace mpm::test
