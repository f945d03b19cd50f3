#pragma once
// Running another program from `mpm` (the yardstick's script, the plotting script): by its
// arguments, never through a shell, so no path needs quoting for one.

#include <string>
#include <vector>

namespace mpm::tools {

struct ProcessResult {
  std::string error;   ///< non-empty: it could not be started (why, e.g. "Permission denied")
  int exit_code = -1;  ///< its exit status, or -1 if a signal ended it
  std::string output;  ///< its standard output and error, if captured
};

/// Runs argv[0] (looked up on PATH unless it holds a '/') with the arguments argv and waits for
/// it; a script without a "#!" line given by its path is run by /bin/sh (as execvp() does).
/// With `capture`, its standard output and standard error are returned instead of shown.
ProcessResult run_process(const std::vector<std::string>& argv, bool capture);

}  // namespace mpm::tools
