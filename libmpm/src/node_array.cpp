#include "mpm/node_array.hpp"

#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <stdexcept>
#include <string>

namespace mpm {

std::size_t PageBuffer::page_size() {
  static const auto size = static_cast<std::size_t>(sysconf(_SC_PAGESIZE));
  return size;
}

PageBuffer::~PageBuffer() {
  if (data_ != nullptr) munmap(data_, bytes_);
}

void PageBuffer::allocate(std::size_t bytes) {
  if (data_ != nullptr) munmap(data_, bytes_);
  data_ = nullptr;
  bytes_ = 0;
  if (bytes == 0) return;
  void* p = mmap(nullptr, bytes, PROT_READ | PROT_WRITE,
                 MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE, -1, 0);
  if (p == MAP_FAILED) {
    throw std::runtime_error("grid: cannot reserve " + std::to_string(bytes) +
                             " bytes of address space for a node array (" + std::strerror(errno) +
                             ")");
  }
  data_ = p;
  bytes_ = bytes;
}

void PageBuffer::release(std::size_t first, std::size_t count) {
  const std::size_t page = page_size();
  const std::size_t begin = (first + page - 1) / page * page;
  const std::size_t end = std::min(first + count, bytes_) / page * page;
  if (end <= begin) return;
  // MADV_DONTNEED on a private anonymous mapping: the pages are freed and read as zeros.
  madvise(static_cast<char*>(data_) + begin, end - begin, MADV_DONTNEED);
}

}  // namespace mpm
