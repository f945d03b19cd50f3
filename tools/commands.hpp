#pragma once
// The subcommands of `mpm`, each a thin layer: options in, library call, report out.

#include <filesystem>
#include <optional>
#include <string>
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

struct VerifyArgs {
  std::vector<std::string> cases;    ///< empty: all
  std::vector<std::string> methods;  ///< empty: every method the case lists
  int resolution = 0;                ///< > 0: only this refinement factor
  bool convergence = false;          ///< every resolution the case lists
  std::filesystem::path json_file;
  std::filesystem::path data_dir;   ///< data/verification
  std::filesystem::path scene_dir;  ///< non-empty: write every scene run there as JSON
  double multiplier_radius = 0.0;   ///< > 0: Blending walls merge Phi's multipliers within it
  std::string update;               ///< non-empty: every case under this update scheme
};

/// `mpm verify`: 0 when every selected check passes, 1 when one fails, 2 bad input.
int verify_command(const VerifyArgs& args);

struct BenchArgs {
  std::string kind;                  ///< "accuracy" or "stability"
  std::vector<std::string> cases;    ///< accuracy: series names; stability: parts (empty: all)
  std::vector<std::string> methods;  ///< empty: every method the configuration lists
  bool smoke = false;                ///< the few configurations ctest runs
  std::filesystem::path config;      ///< data/bench/<kind>.json
  std::filesystem::path csv_file;
  std::filesystem::path plot_file;  ///< PNG, drawn by scripts/bench_plot.py
  std::filesystem::path failures;   ///< stability: where failing scenes are written
  std::filesystem::path scripts_dir;
  unsigned seed = 1;
  int runs = 0;  ///< stability: random wall placements (0: the configuration's count)
};

struct PerfArgs {
  int cells = 32;  ///< the block's cells per side (8 particles per cell)
  int steps = 20;  ///< timed steps per round (after `settle` settling steps)
  int settle = 5;  ///< steps each scene takes before its timed rounds (the scaling runs: 1)
  /// Rounds per scene, interleaved with the other scenes' (median); unset: 5, or 1 with `smoke`.
  std::optional<int> rounds;
  double yardstick = 0.0;  ///< > 0: the yardstick's M particle-steps/s, same session
  /// Non-empty: the yardstick's script (../shared/tools/yardstick/run.sh), run once per round
  /// of the standard block, interleaved with its rounds (instead of `yardstick`).
  std::filesystem::path yardstick_script;
  bool smoke = false;  ///< a tiny block, 2 steps a round (the test suite's run)
  std::filesystem::path json_file;
};

/// `mpm bench perf`: issue 9's step targets (throughput, parallel speed-up, the dual-grid floor
/// against the standard one, memory per particle, scaling) timed in one run; 0, or 1 when a run
/// faulted or a later round of the yardstick failed, 2 when the yardstick's script cannot be
/// run or prints no rate for the thread count, 4 when the JSON cannot be written.
int perf_command(const PerfArgs& args);

/// `mpm bench accuracy|stability`: 0 when no run failed (a numerical fault or non-finite error;
/// stability: any failure class), 1 when one did, 2 bad input, 4 cannot write.
int bench_command(const BenchArgs& args);

}  // namespace mpm::tools
