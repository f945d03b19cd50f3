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

/// A fixed-size array of plain values (int, double: all-zero bytes are 0, no destructor to run)
/// over its own PageBuffer, zero at assign_zero(): a per-node map that costs memory only where
/// it is written (the couplings' node -> row maps, node_row()).
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
  /// Returns the whole pages inside bytes [first, first + count) to the system: their values
  /// read as zero again.
  void release(std::size_t first, std::size_t count) { buffer_.release(first, count); }
  T& operator[](std::size_t i) { return data()[i]; }
  const T& operator[](std::size_t i) const { return data()[i]; }
  T* data() { return static_cast<T*>(buffer_.data()); }
  const T* data() const { return static_cast<const T*>(buffer_.data()); }

 private:
  PageBuffer buffer_;
  std::size_t size_ = 0;
};

/// One of the grid's node arrays inside a PageBuffer that holds all of them (Grid). Values are
/// stored by blocks of 2^shift nodes: value i is at byte (i >> shift) block_stride +
/// (i % 2^shift) sizeof(T) from `first`. With block_stride = 2^shift sizeof(T) that is a plain
/// array (the dense layout); with block_stride the bytes of every array's block together, a
/// block's values of all the arrays are one run of memory (the sparse layout), so that a page
/// holds whole blocks of every array rather than eight blocks' masses and 2.7 blocks' vectors.
/// Nodes within one block are adjacent: code may step through a row of them by pointer.
template <class T>
class NodeField {
  static_assert(std::is_trivially_destructible_v<T>, "node values must be plain data");

 public:
  using value_type = T;
  void view(void* first, std::size_t n, int shift, std::size_t block_stride) {
    base_ = static_cast<char*>(first);
    size_ = n;
    shift_ = shift;
    mask_ = (std::size_t{1} << shift) - 1;
    block_stride_ = block_stride;
  }
  [[nodiscard]] std::size_t size() const { return size_; }
  /// The first value's address (node i is at byte_offset(i) from it: Grid::byte_offset()).
  [[nodiscard]] char* base() const { return base_; }
  /// The same values with the layout fixed at compile time, for the transfers' inner loops
  /// (operator[] reads the layout from the object: a few more instructions per node):
  /// Blocked, blocks of 2^Shift nodes BlockBytes apart; otherwise a plain array. It must be the
  /// layout view() was given. Writable, as the field it comes from.
  template <bool Blocked, int Shift, std::size_t BlockBytes>
  struct Access {
    char* base;
    T& operator[](std::size_t i) const {
      if constexpr (Blocked) {
        constexpr std::size_t kMask = (std::size_t{1} << Shift) - 1;
        return *reinterpret_cast<T*>(base + (i >> Shift) * BlockBytes + (i & kMask) * sizeof(T));
      } else {
        return reinterpret_cast<T*>(base)[i];
      }
    }
  };
  template <bool Blocked, int Shift, std::size_t BlockBytes>
  [[nodiscard]] Access<Blocked, Shift, BlockBytes> access() const {
    return {base_};
  }
  T& operator[](std::size_t i) {
    return *reinterpret_cast<T*>(base_ + (i >> shift_) * block_stride_ + (i & mask_) * sizeof(T));
  }
  const T& operator[](std::size_t i) const {
    return *reinterpret_cast<const T*>(base_ + (i >> shift_) * block_stride_ +
                                       (i & mask_) * sizeof(T));
  }

 private:
  char* base_ = nullptr;
  std::size_t size_ = 0;
  int shift_ = 0;
  std::size_t mask_ = 0;
  std::size_t block_stride_ = sizeof(T);
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
