// The temporary file a fuzz target writes its input to (the loaders read files).
#pragma once

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <string>

// One per process (fork-mode runs share the directory). run_fuzzer.sh's seeded runs set
// MPM_FUZZ_FIXED_NAME for one name in every run: a name made of the pid changed the coverage a
// run saw, and the runs were not reproducible.
inline std::filesystem::path fuzz_file(const std::string& stem, const std::string& extension) {
  if (std::getenv("MPM_FUZZ_FIXED_NAME") != nullptr) {
    return std::filesystem::temp_directory_path() / (stem + extension);
  }
  return std::filesystem::temp_directory_path() /
         (stem + "_" + std::to_string(::getpid()) + extension);
}
