#pragma once
// The temporary directory, for the files the tests, the benchmarks and `mpm bench` / `mpm verify`
// write for themselves (meshes, working folders).

#include <cstdlib>
#include <filesystem>
#include <stdexcept>
#include <string>

namespace mpm::test {

/// std::filesystem::temp_directory_path(); where there is none to use (TMPDIR naming a file, or
/// a path that does not exist), std::runtime_error naming TMPDIR and why, for `purpose` ("the
/// floor's mesh": "no temporary directory for the floor's mesh (TMPDIR='...': Not a directory)").
inline std::filesystem::path temporary_directory(const std::string& purpose) {
  try {
    return std::filesystem::temp_directory_path();
  } catch (const std::filesystem::filesystem_error& e) {
    const char* tmpdir = std::getenv("TMPDIR");
    throw std::runtime_error("no temporary directory for " + purpose + " (TMPDIR='" +
                             std::string(tmpdir != nullptr ? tmpdir : "") +
                             "': " + e.code().message() + ")");
  }
}

}  // namespace mpm::test
