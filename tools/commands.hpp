#pragma once
// The subcommands of `mpm`, each a thin layer: options in, library call, report out.

#include <filesystem>
#include <optional>
#include <vector>

#include "mpm/boundary_package.hpp"

namespace mpm::tools {

struct PrepArgs {
  std::filesystem::path mesh;
  std::filesystem::path output;  ///< OUT.h5; OUT.xmf is written next to it
  double spacing = 0.0;
  std::vector<double> origin;   ///< grid box minimum (3); default: fits the mesh
  std::vector<double> box_max;  ///< grid box maximum (3); default: fits the mesh
  std::string shape = "bspline2";
  bool overwrite = false;
  PrepOptions options;
};

/// `mpm prep`: returns the process exit code (0, 2 bad input, 4 cannot write).
int prep_command(const PrepArgs& args);

}  // namespace mpm::tools
