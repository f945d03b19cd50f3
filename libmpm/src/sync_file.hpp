#pragma once
// Putting a file on the disk (internal to libmpm).

#include <fcntl.h>
#include <unistd.h>

#include <filesystem>

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

}  // namespace mpm::detail
