// The temporary file a fuzz target writes its input to (the loaders read files).
#pragma once

#include <unistd.h>

#include <algorithm>
#include <cstddef>
#include <cstdlib>
#include <filesystem>
#include <string>

// One per process, and of the same length in every process (the pid padded to 12 digits), so
// that no run's coverage depends on how many digits its pid has: run_fuzzer.sh's runs from a
// fixed seed are then reproducible.
inline std::filesystem::path fuzz_file(const std::string& stem, const std::string& extension) {
  if (std::getenv("MPM_FUZZ_FIXED_NAME") != nullptr) {
    return std::filesystem::temp_directory_path() / (stem + extension);
  }
  std::string pid = std::to_string(::getpid());
  pid.insert(0, 12 - std::min<std::size_t>(pid.size(), 12), '0');
  return std::filesystem::temp_directory_path() / (stem + "_" + pid + extension);
}
