#pragma once
// Checkpoints: everything a run needs to continue bit for bit, as named flat arrays in one HDF5
// file written aside and renamed into place, so a killed process leaves either the previous
// checkpoint or the new one, never half of one. HDF5 stays inside checkpoint.cpp.

#include <cstdint>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

namespace mpm {

struct Checkpoint {
  std::map<std::string, std::vector<double>> reals;
  std::map<std::string, std::vector<std::int64_t>> integers;
  std::map<std::string, std::string> texts;

  /// The named array; throws std::runtime_error naming the key when it is missing or, with
  /// size > 0, of another length.
  [[nodiscard]] const std::vector<double>& real(const std::string& key, std::size_t size = 0) const;
  [[nodiscard]] const std::vector<std::int64_t>& integer(const std::string& key,
                                                         std::size_t size = 0) const;
  [[nodiscard]] const std::string& text(const std::string& key) const;
};

/// Writes FILE.tmp, flushes and closes it, then renames it over FILE.
void write_checkpoint(const std::filesystem::path& file, const Checkpoint& checkpoint);
/// Throws std::runtime_error naming the file when it cannot be read. `texts_only` skips the
/// arrays (the particle state), for a caller that needs only, say, the scene path.
Checkpoint read_checkpoint(const std::filesystem::path& file, bool texts_only = false);

}  // namespace mpm
