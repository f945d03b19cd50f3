#pragma once
// The run loop behind `mpm run`: time stepping, particle snapshots, the energy/force history and
// the summary.

#include <filesystem>
#include <string>

#include "mpm/scene.hpp"

namespace mpm {

struct RunOptions {
  std::filesystem::path out_dir;
  bool overwrite = false;  ///< replace an earlier result in out_dir
  bool quiet = false;      ///< no progress display
  /// Continue the run in out_dir from its checkpoint.h5 (written with every particle frame):
  /// frames and history rows after the checkpoint are dropped and computed again.
  bool resume = false;
  /// For tests: stop after this many steps as a killed process would (no summary.json).
  long halt_after_steps = -1;
};

/// Exit codes: 0 done, 2 bad input (nothing written), 3 numerical fault (outputs up to the fault
/// kept, summary says why), 4 output could not be written.
enum ExitCode : int { kExitOk = 0, kExitBadInput = 2, kExitFault = 3, kExitIo = 4 };

/// Runs the scene and writes OUT/particles.h5 + particles.xmf, OUT/history.csv,
/// OUT/checkpoint.h5 and OUT/summary.json. Problems are reported as one line on stderr; returns
/// an ExitCode.
int run_scene(const Scene& scene, const RunOptions& options);

/// What a checkpoint in out_dir was written for (for `mpm run --resume OUTDIR`): the scene file
/// and its refinement (`mpm run --resolution`; 1 for a checkpoint written before the option),
/// read from the file once. Throws std::runtime_error naming the file when there is no
/// readable checkpoint.
struct CheckpointOrigin {
  std::filesystem::path scene;
  int resolution = 1;
};
CheckpointOrigin checkpoint_origin(const std::filesystem::path& out_dir);

}  // namespace mpm
