#pragma once
// Putting a file on the disk, and replacing one whole (internal to libmpm).

#include <fcntl.h>
#include <unistd.h>

#include <filesystem>
#include <system_error>

namespace mpm::detail {

// Asks the kernel to put a file (or a directory's entries) on the disk: closing or flushing a
// file hands the data to the operating system only, so a power cut after a rename could leave a
// file whose name is there and whose contents are not.
inline bool sync_to_disk(const std::filesystem::path& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return false;
  const bool synced = ::fsync(fd) == 0;
  ::close(fd);
  return synced;
}

// Writes `file` aside, to FILE.tmp through `write(tmp)` (false on failure), and renames it over
// the old one, so a reader, or a process killed at any moment, finds the old file or the new one
// whole. `durable`: the new file on the disk before it takes the name, and the name after (a
// power cut too leaves one or the other). False on any failure, the temporary file removed.
template <class Write>
bool replace_file(const std::filesystem::path& file, Write&& write, bool durable) {
  std::filesystem::path tmp = file;
  tmp += ".tmp";
  std::error_code error;
  bool good = write(tmp) && (!durable || sync_to_disk(tmp));
  if (good) std::filesystem::rename(tmp, file, error);
  good = good && !error;
  if (good && durable) {
    good = sync_to_disk(file.has_parent_path() ? file.parent_path() : std::filesystem::path("."));
  }
  if (!good) std::filesystem::remove(tmp, error);
  return good;
}

}  // namespace mpm::detail
