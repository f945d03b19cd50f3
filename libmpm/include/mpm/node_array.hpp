#pragma once
// Grid node arrays whose memory is taken from the operating system page by page, as the nodes
// are written: the grid's address space covers the scene's whole box, but only the pages of
// the blocks that have held particles are backed by memory, and release() hands idle pages
// back (they read as zeros again). Linux (mmap, madvise).

#include <cstddef>
#include <type_traits>
#include <utility>
#include <vector>

namespace mpm {

/// Zero-initialised anonymous memory, reserved but not committed (MAP_NORESERVE): untouched
/// pages cost nothing and read as zeros.
class PageBuffer {
 public:
  PageBuffer() = default;
  PageBuffer(const PageBuffer&) = delete;
  PageBuffer& operator=(const PageBuffer&) = delete;
  PageBuffer(PageBuffer&& other) noexcept { swap(other); }
  PageBuffer& operator=(PageBuffer&& other) noexcept {
    PageBuffer moved(std::move(other));
    swap(moved);
    return *this;
  }
  ~PageBuffer();

  /// Maps `bytes` of fresh zeros (the old mapping, if any, is dropped). Throws
  /// std::runtime_error naming the size when the address space is not available.
  void allocate(std::size_t bytes);
  /// Returns the whole pages inside [first, first + count) bytes to the system; they read as
  /// zeros afterwards. The caller zeroes any partial page itself.
  void release(std::size_t first, std::size_t count);
  [[nodiscard]] void* data() const { return data_; }
  [[nodiscard]] std::size_t bytes() const { return bytes_; }
  static std::size_t page_size();

 private:
  void swap(PageBuffer& other) noexcept {
    std::swap(data_, other.data_);
    std::swap(bytes_, other.bytes_);
  }
  void* data_ = nullptr;
  std::size_t bytes_ = 0;
};

/// A fixed-size array of plain values (int, double, Eigen fixed-size vectors of doubles: all-zero
/// bytes are 0, no destructor to run) over a PageBuffer, zero at assign_zero(): the part of
/// std::vector's interface the grid uses.
template <class T>
class NodeArray {
  static_assert(std::is_trivially_destructible_v<T>, "node values must be plain data");

 public:
  using value_type = T;
  /// n values, all zero bits (0.0 for doubles and Eigen vectors).
  void assign_zero(std::size_t n) {
    buffer_.allocate(n * sizeof(T));
    size_ = n;
  }
  [[nodiscard]] std::size_t size() const { return size_; }
  T& operator[](std::size_t i) { return data()[i]; }
  const T& operator[](std::size_t i) const { return data()[i]; }
  T* data() { return static_cast<T*>(buffer_.data()); }
  const T* data() const { return static_cast<const T*>(buffer_.data()); }
  T* begin() { return data(); }
  T* end() { return data() + size_; }
  const T* begin() const { return data(); }
  const T* end() const { return data() + size_; }
  /// Returns the whole pages inside bytes [first, first + count) (see PageBuffer::release).
  void release_bytes(std::size_t first, std::size_t count) { buffer_.release(first, count); }

 private:
  PageBuffer buffer_;
  std::size_t size_ = 0;
};

/// Compact row numbers for a few of a grid's nodes (a coupling's rows) without a grid-sized
/// initialisation or reset: `rows` lists the nodes in row order and `row_of` (page-backed:
/// memory only for the pages of nodes that have had a row) points back; an entry is valid when
/// rows[row_of[node]] == node, so forgetting every row is clearing `rows`. Returns the node's
/// row, giving it the next one if it has none.
inline int node_row(NodeArray<int>& row_of, std::vector<int>& rows, int node) {
  int& r = row_of[static_cast<std::size_t>(node)];
  if (static_cast<std::size_t>(r) < rows.size() && rows[static_cast<std::size_t>(r)] == node) {
    return r;
  }
  r = static_cast<int>(rows.size());
  rows.push_back(node);
  return r;
}

}  // namespace mpm
