#pragma once
// The standard Cartesian grid (the A-grid) as flat arrays, and the per-particle stencil of
// tensor-product weights over it.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

#include "mpm/node_array.hpp"
#include "mpm/shape.hpp"
#include "mpm/types.hpp"

namespace mpm {

/// Ghost node layers the solver adds beyond each face of the scene's grid box, so the widest
/// kernel (B-spline, GIMP: 3 nodes) never leaves the grid and walls have nodes to mirror into.
inline constexpr int kGhostLayers = 2;

/// A node's velocities at the start of the step and after the forces: v = p / m and
/// v_new = v + dt f / m above the mass threshold, zero below it (both grids' update).
template <int D>
void node_velocities(double m, const Vec<D>& momentum, const Vec<D>& force, double dt,
                     double threshold, Vec<D>& velocity, Vec<D>& velocity_new) {
  if (m > threshold) {
    velocity = momentum / m;
    velocity_new = velocity + dt * force / m;
  } else {
    velocity.setZero();
    velocity_new.setZero();
  }
}

/// The standard Cartesian grid (the A-grid) as flat node arrays, in one of two layouts:
/// - dense: node index sum_d i_d stride_d, last axis fastest (for a box the material fills);
/// - sparse: by blocks of kBlock^D nodes, a node's index its block's place in storage times
///   kBlockNodes plus its place in the block (last axis fastest), so that a block's nodes are
///   one contiguous run of every array; and a block's five arrays are stored together
///   (kBlockBytes, 6.5 kB in 3D: NodeField), so a page holds parts of at most two or three
///   blocks. Blocks are stored in Morton (Z) order, so neighbouring blocks in storage are
///   neighbours in every direction, not a column along one axis. The storage spans the box in
///   address space (more: Morton order pads each axis to a power of two), but memory backs only
///   the pages of blocks that have held particles (PageBuffer), and pages whose blocks have
///   been idle for kReleaseAfter steps are handed back. A hillside's box is mostly air: its grid
///   then costs what the flow covers, not what the box holds.
/// Both layouts number nodes separably (linear(i) = sum_d axis_offset(d, i_d)); code that
/// forms node indices through linear(), axis_offset() or the Stencil serves both.
template <int D>
struct Grid {
  Vec<D> origin = Vec<D>::Zero();  ///< position of node (0,...,0)
  double h = 1.0;                  ///< node spacing
  double inv_h = 1.0;
  Index<D> nodes = Index<D>::Ones();  ///< nodes per axis (the box; storage is padded to blocks)

  NodeField<double> mass;
  /// Under MLS-MPM the momentum after the force, p_I + dt f_I, with the force left at zero (so
  /// `velocity` is v_I^{n+1} too; nothing reads v_I^n under MLS: Solver::scatter()).
  NodeField<Vec<D>> momentum;
  NodeField<Vec<D>> force;
  NodeField<Vec<D>> velocity;      ///< v_I^n = p_I / m_I (before the force update)
  NodeField<Vec<D>> velocity_new;  ///< v_I^{n+1} after forces and wall conditions
  /// The five arrays' memory: dense, one array after the other; sparse, block by block (a
  /// block's masses, then its momenta, forces, velocities and new velocities: kBlockBytes).
  PageBuffer storage;
  /// 3D: per node, whether the 3^3 nodes from it on (the stencil of a 3-node kernel whose
  /// first node it is) all carry mass above the gather's threshold, as a gather found it since
  /// the masses last changed: +stencil_epoch, yes; -stencil_epoch, no; anything else, not known
  /// (sample_grid(): the particles of a step share each first node about 8 times, so 1 in 8
  /// pays the 27 mass checks, and MUSL's second gather none). Written by several threads at
  /// once, the same answer from each (relaxed atomics). One byte per node slot, page-backed
  /// (sparse: a block's marks are 64 bytes in storage order, and a page of them is returned
  /// with the blocks it covers: release_idle()); when the epoch wraps, the whole array is
  /// mapped afresh (zeros: not known).
  NodeArray<std::int8_t> stencil_mark;
  int stencil_epoch = 0;  ///< 0: no marks may be used (no masses_changed() yet)
  /// Bytes of stencil_mark per node (3D only).
  static constexpr std::size_t kMarkBytes = D == 3 ? 1 : 0;
  /// Every write of the node masses must be followed by this (the particles-to-grid scatter
  /// is the only one): the marks found before no longer hold.
  void masses_changed() {
    if constexpr (D == 3) {
      if (++stencil_epoch > 127) {
        stencil_mark.assign_zero(stencil_mark.size());
        stencil_epoch = 1;
      }
    }
  }

  static constexpr int kBlock = 4;
  static constexpr int kBlockNodes = D == 1 ? 4 : D == 2 ? 16 : 64;  ///< kBlock^D
  static constexpr int kBlockShift = D == 1 ? 2 : D == 2 ? 4 : 6;    ///< log2(kBlockNodes)
  /// Steps a block stays idle before its pages may be returned (a flow that comes back soon
  /// does not pay the page faults again).
  static constexpr int kReleaseAfter = 32;
  /// Bytes per node over the five arrays.
  static constexpr std::size_t kNodeBytes = sizeof(double) + 4 * sizeof(Vec<D>);
  /// Bytes of one block of the sparse layout (all five arrays). A multiple of 16, as every
  /// array's part of it: Eigen's 2-vectors may be accessed aligned.
  static constexpr std::size_t kBlockBytes = kBlockNodes * kNodeBytes;
  static_assert(kBlockNodes * sizeof(double) % 16 == 0 && kBlockBytes % 16 == 0);

  /// A node array with its layout fixed at compile time (NodeField::Access): Sparse must be
  /// the grid's `sparse`.
  template <bool Sparse, class T>
  [[nodiscard]] auto access(const NodeField<T>& array) const {
    return array.template access<Sparse, kBlockShift, kBlockBytes>();
  }

  /// Where node index i's value lies in one of the node arrays whose values take Size bytes,
  /// from the array's base(). Additive as node indices are: the offsets of the per-axis parts
  /// (axis_offset(d, i_d)) sum to the node's, since in the sparse layout the axes' parts of an
  /// index are disjoint bit fields of its block and of its place in the block.
  template <std::size_t Size>
  [[nodiscard]] std::ptrdiff_t byte_offset(int i) const {
    const auto n = static_cast<std::ptrdiff_t>(i);
    if (!sparse) return n * static_cast<std::ptrdiff_t>(Size);
    return (n >> kBlockShift) * static_cast<std::ptrdiff_t>(kBlockBytes) +
           (n & (kBlockNodes - 1)) * static_cast<std::ptrdiff_t>(Size);
  }

  void resize(const Vec<D>& grid_origin, double spacing, const Index<D>& node_count,
              bool sparse_layout = false) {
    sparse = sparse_layout;
    origin = grid_origin;
    h = spacing;
    inv_h = 1.0 / spacing;
    nodes = node_count;
    for (int d = 0; d < D; ++d) {
      blocks[d] = (nodes[d] + kBlock - 1) / kBlock;
      halves[d] = (nodes[d] + 1) / 2;
    }
    // Per-axis offsets: dense, i stride_d; sparse, kBlockNodes times the Morton spread of the
    // block coordinate i / 4 (its bits moved to the axis's bit positions: disjoint, so the
    // block's Morton index is the sum over the axes) plus (i % 4) times the in-block stride.
    // Bit positions are dealt round the axes, lowest bits first and the last axis first in each
    // round, skipping an axis once its coordinates have no more bits: a flat box's blocks then
    // fill the index range to within a factor of 2 per axis, not up to the longest axis cubed.
    {
      int bits[D], next = 0;
      for (int d = 0; d < D; ++d) {
        bits[d] = 0;
        while ((blocks[d] - 1) >> bits[d]) ++bits[d];
        bit_position[d].clear();
      }
      for (int k = 0; k < 31; ++k) {
        for (int d = D - 1; d >= 0; --d) {
          if (k < bits[d]) bit_position[d].push_back(next++);
        }
      }
    }
    long last_block = 0;  // Morton index of the last block: the largest
    for (int d = 0; d < D; ++d) last_block += spread(d, blocks[d] - 1);
    const long slots = sparse ? (last_block + 1) * kBlockNodes : nodes.template cast<long>().prod();
    if (slots > std::numeric_limits<int>::max()) {
      throw std::runtime_error("grid: " + std::to_string(slots) +
                               " node slots in the sparse layout exceed the index range; use "
                               "\"storage\": \"dense\" or a larger spacing");
    }
    slot_count = static_cast<std::size_t>(slots);
    for (int d = D - 1, dense = 1, local = 1; d >= 0; --d) {
      local_stride[d] = sparse ? local : dense;
      dense *= nodes[d];
      local *= kBlock;
    }
    for (int d = 0; d < D; ++d) {
      offset_table[d].resize(static_cast<std::size_t>(nodes[d]));
      for (int i = 0; i < nodes[d]; ++i) {
        offset_table[d][static_cast<std::size_t>(i)] =
            sparse ? static_cast<int>(kBlockNodes * spread(d, i / kBlock) +
                                      (i % kBlock) * local_stride[d])
                   : i * local_stride[d];
      }
    }
    const auto block_count = static_cast<std::size_t>(blocks.prod());
    storage_block.resize(sparse ? block_count : 0);  // the dense layout has no use for it
    for (std::size_t b = 0; b < storage_block.size(); ++b) {
      Index<D> c;
      auto rest = static_cast<int>(b);
      for (int d = D - 1; d >= 0; --d) {
        c[d] = rest % blocks[d];
        rest /= blocks[d];
      }
      storage_block[b] = linear((c * kBlock).eval()) / kBlockNodes;
    }
    const auto n = size();
    // Each array's part: sparse, of a block (the blocks follow each other, kBlockBytes apart);
    // dense, the whole array (rounded to 64 bytes), the arrays one after the other.
    auto part = [&](std::size_t size) {
      return sparse ? kBlockNodes * size : (n * size + 63) / 64 * 64;
    };
    storage.allocate(sparse ? n / kBlockNodes * kBlockBytes
                            : part(sizeof(double)) + 4 * part(sizeof(Vec<D>)));
    char* at = static_cast<char*>(storage.data());
    auto place = [&](auto& array) {
      using T = typename std::decay_t<decltype(array)>::value_type;
      array.view(at, n, kBlockShift, sparse ? kBlockBytes : kBlockNodes * sizeof(T));
      at += part(sizeof(T));
    };
    place(mass);
    place(momentum);
    place(force);
    place(velocity);
    place(velocity_new);
    if constexpr (D == 3) {  // whole pages, so that release_idle() can return the last one
      const std::size_t page = PageBuffer::page_size();
      stencil_mark.assign_zero((n + page - 1) / page * page);
    }
    stencil_epoch = 0;
    block_active.assign(block_count, 0);
    half_marked.assign(static_cast<std::size_t>(halves.prod()), 0);
    const std::size_t stored = sparse ? slot_count / kBlockNodes : 0;  // pages: sparse only
    last_active.assign(stored, -(1 << 30));
    resident.assign(stored, 0);
    mark_resident.assign(
        (stored * kBlockNodes * kMarkBytes + PageBuffer::page_size() - 1) / PageBuffer::page_size(),
        0);
    epoch = 0;
    peak_committed = active_at_peak = peak_active = 0;
    active_blocks.clear();
    previous_blocks.clear();
  }
  /// Node slots in storage. Sparse: the box padded up to whole blocks and the block counts to
  /// the Morton index range; the slots outside the box hold zeros and never carry mass (and,
  /// never written, take no memory).
  [[nodiscard]] std::size_t size() const { return slot_count; }
  /// Nodes in the box.
  [[nodiscard]] std::size_t node_count() const { return static_cast<std::size_t>(nodes.prod()); }
  /// Bytes the box would take stored densely (the node arrays and the stencil marks).
  [[nodiscard]] std::size_t box_bytes() const { return node_count() * (kNodeBytes + kMarkBytes); }
  /// What node index i_d along axis d adds to a node's index (indices are separable: the index
  /// of node i is the sum over the axes).
  [[nodiscard]] int axis_offset(int d, int i) const {
    return offset_table[d][static_cast<std::size_t>(i)];
  }
  /// Block coordinate x along axis d with its bits moved to the axis's Morton bit positions.
  [[nodiscard]] long spread(int d, int x) const {
    long out = 0;
    for (std::size_t k = 0; k < bit_position[d].size(); ++k) {
      out |= static_cast<long>((x >> k) & 1) << bit_position[d][k];
    }
    return out;
  }
  [[nodiscard]] int linear(const Index<D>& i) const {
    int n = 0;
    for (int d = 0; d < D; ++d) n += axis_offset(d, i[d]);
    return n;
  }
  [[nodiscard]] Index<D> multi(int linear_index) const {
    if (!sparse) return lattice_index<D>(linear_index, nodes);
    Index<D> i;
    const long block = linear_index / kBlockNodes;
    int local = linear_index % kBlockNodes;
    for (int d = D - 1; d >= 0; --d) {
      int b = 0;  // de-interleave the Morton index
      for (std::size_t k = 0; k < bit_position[d].size(); ++k) {
        b |= static_cast<int>((block >> bit_position[d][k]) & 1) << k;
      }
      i[d] = b * kBlock + local % kBlock;
      local /= kBlock;
    }
    return i;
  }
  /// Is node i in the box? (multi() of a storage slot outside it, the sparse layout's block
  /// padding and Morton holes, is not.)
  [[nodiscard]] bool in_box(const Index<D>& i) const { return (i.array() < nodes.array()).all(); }
  [[nodiscard]] Vec<D> position(const Index<D>& i) const {
    return origin + h * i.template cast<double>();
  }

  // Activity by blocks. Each step marks the blocks within reach of a particle (the nodes
  // within two of its cell: every kernel's stencil); clearing, the grid update and the MUSL
  // remap then run over those blocks only, and every node outside them holds zeros.
  // The particles mark half-blocks (2^D nodes: one store each); a block is active when a marked
  // half-block lies within reach: node i's particles reach nodes i-2..i+2, so the block of nodes
  // 4b..4b+3 is reached from the half-blocks 2b-1..2b+2.
  Index<D> blocks = Index<D>::Ones();        ///< blocks per axis
  Index<D> halves = Index<D>::Ones();        ///< half-blocks per axis
  bool sparse = false;                       ///< the layout (see the struct's comment)
  std::size_t slot_count = 0;                ///< size()
  Index<D> local_stride = Index<D>::Ones();  ///< dense: the strides; sparse: within a block
  std::vector<int> offset_table[D];          ///< axis_offset(d, i)
  std::vector<int> bit_position[D];          ///< sparse: where bit k of a block coordinate goes
  std::vector<int> storage_block;            ///< sparse: block (index order) -> place in storage
  std::vector<std::uint8_t> block_active;    ///< this step's flags
  std::vector<std::uint8_t> half_marked;     ///< this step's particles' half-blocks
  std::vector<int> active_blocks;            ///< this step's blocks, in index order
  std::vector<int> previous_blocks;          ///< the step before's (clear_previous() zeroes them)
  // Sparse only, by place in storage (Morton order, holes included).
  std::vector<int> last_active;             ///< the last step (epoch) each block was active
  std::vector<std::uint8_t> resident;       ///< may the block's pages hold memory?
  std::vector<std::uint8_t> mark_resident;  ///< may this page of stencil_mark hold memory?
  int epoch = 0;                            ///< steps marked so far
  /// Sampled by release_idle(): the most memory the node arrays held, the active blocks' need
  /// then, and the most the active blocks needed at any sample.
  std::size_t peak_committed = 0, active_at_peak = 0, peak_active = 0;

  /// Linear index of the block with per-axis indices b (last axis fastest, as nodes).
  [[nodiscard]] int block_index(const Index<D>& b) const {
    return static_cast<int>(lattice_offset<D>(b, blocks));
  }
  /// The block holding a node.
  [[nodiscard]] int block_of(int node) const {
    return block_index((multi(node).array() / kBlock).matrix());
  }
  /// Starts a step's marking: the last step's blocks become the previous ones.
  void begin_marking() {
    for (const int b : active_blocks) block_active[static_cast<std::size_t>(b)] = 0;
    std::swap(previous_blocks, active_blocks);
    active_blocks.clear();
    std::fill(half_marked.begin(), half_marked.end(), std::uint8_t{0});
    ++epoch;
  }
  /// Marks the half-block of the cell of x. Safe to call from several threads at once.
  void mark(const Vec<D>& x) {
    int linear_half = 0;
    for (int d = 0; d < D; ++d) {
      const int i = static_cast<int>(std::floor((x[d] - origin[d]) * inv_h));
      linear_half = linear_half * halves[d] + std::clamp(i, 0, nodes[d] - 1) / 2;
    }
    std::atomic_ref<std::uint8_t>(half_marked[static_cast<std::size_t>(linear_half)])
        .store(1, std::memory_order_relaxed);
  }
  /// Ends the marking: the blocks the marked half-blocks reach, listed in index order.
  void finish_marking() {
    Index<D> c = Index<D>::Zero();
    for (std::size_t k = 0; k < half_marked.size(); ++k) {
      if (half_marked[k] != 0) {
        Index<D> lo, hi;
        for (int d = 0; d < D; ++d) {
          lo[d] = c[d] >= 1 ? (c[d] - 1) / 2 : 0;
          hi[d] = std::min((c[d] + 1) / 2, blocks[d] - 1);
        }
        for_each_in_box(lo, hi, [&](const Index<D>& b) {
          block_active[static_cast<std::size_t>(block_index(b))] = 1;
        });
      }
      for (int d = D - 1; d >= 0 && ++c[d] == halves[d]; --d) c[d] = 0;
    }
    for (std::size_t b = 0; b < block_active.size(); ++b) {
      if (block_active[b] == 0) continue;
      active_blocks.push_back(static_cast<int>(b));
      if (!sparse) continue;
      const auto s = static_cast<std::size_t>(storage_block[b]);
      last_active[s] = epoch;
      resident[s] = 1;
      if constexpr (kMarkBytes > 0) {
        mark_resident[s * kBlockNodes * kMarkBytes / PageBuffer::page_size()] = 1;
      }
    }
  }
  /// Calls f(first, count) for each run of nodes of `block` contiguous in memory: sparse, one,
  /// the whole block (padding slots past the box included: they have no mass); dense, one per
  /// row along the last axis.
  template <class F>
  void for_each_run(int block, F&& f) const {
    if (sparse) {
      f(storage_block[static_cast<std::size_t>(block)] * kBlockNodes, kBlockNodes);
      return;
    }
    Index<D> b;
    for (int d = D - 1; d >= 0; --d) {
      b[d] = block % blocks[d];
      block /= blocks[d];
    }
    Index<D> lo, hi;
    for (int d = 0; d < D; ++d) {
      lo[d] = b[d] * kBlock;
      hi[d] = std::min(lo[d] + kBlock, nodes[d]);
    }
    const int count = hi[D - 1] - lo[D - 1];
    Index<D> i = lo;
    while (true) {
      f(linear(i), count);
      int d = D - 2;
      while (d >= 0 && i[d] + 1 == hi[d]) {
        i[d] = lo[d];
        --d;
      }
      if (d < 0) break;
      ++i[d];
    }
  }
  /// Calls f(node) for every node of `block`.
  template <class F>
  void for_each_node(int block, F&& f) const {
    for_each_run(block, [&](int first, int count) {
      for (int n = first; n < first + count; ++n) f(static_cast<std::size_t>(n));
    });
  }
  /// Zeroes what the last step left in its block previous_blocks[k] for the particles-to-grid
  /// transfer: mass, momentum and force, and the velocities if this step does not have the
  /// block (so that every node outside the active blocks is zero). After the marking; the
  /// blocks are disjoint, so they may be cleared in parallel.
  void clear_previous(std::size_t k) {
    const int b = previous_blocks[k];
    const bool stays = block_active[static_cast<std::size_t>(b)] != 0;
    for_each_run(b, [&](int first, int count) {  // a run is adjacent in every array
      const auto n = static_cast<std::size_t>(first);
      std::fill_n(&mass[n], count, 0.0);
      std::fill_n(&momentum[n], count, Vec<D>::Zero());
      std::fill_n(&force[n], count, Vec<D>::Zero());
      if (stays) return;
      std::fill_n(&velocity[n], count, Vec<D>::Zero());
      std::fill_n(&velocity_new[n], count, Vec<D>::Zero());
    });
  }
  /// Every kReleaseAfter / 2 steps, returns to the system the pages of the arrays that hold
  /// only blocks idle for kReleaseAfter steps or more (they are all zero: clear_previous()).
  /// Serial, after the clearing; touches only blocks that may hold memory. Sparse layout only
  /// (a dense one only samples its memory).
  void release_idle() {
    if (epoch % (kReleaseAfter / 2) != 0 && epoch != 1) return;
    // Memory is at its most just before a release: sample it there.
    const std::size_t committed = committed_bytes();
    if (committed > peak_committed) {
      peak_committed = committed;
      active_at_peak = active_bytes();
    }
    peak_active = std::max(peak_active, active_bytes());
    if (!sparse) return;
    auto idle = [&](std::size_t b) { return last_active[b] + kReleaseAfter <= epoch; };
    const std::size_t page = PageBuffer::page_size();
    const std::size_t count = resident.size();
    for (std::size_t b = 0; b < count; ++b) {
      if (resident[b] == 0 || !idle(b)) continue;
      // The pages that overlap block b; a page is returned when every block it overlaps is idle.
      const std::size_t first_page = b * kBlockBytes / page;
      const std::size_t last_page = ((b + 1) * kBlockBytes - 1) / page;
      bool all = true;
      for (std::size_t p = first_page; p <= last_page; ++p) {
        const std::size_t lo = p * page / kBlockBytes;
        const std::size_t hi = std::min(count - 1, ((p + 1) * page - 1) / kBlockBytes);
        bool free = true;
        for (std::size_t c = lo; c <= hi && free; ++c) free = idle(c);
        if (free) {
          storage.release(p * page, page);
        } else {
          all = false;
        }
      }
      if (all) resident[b] = 0;
    }
    // The stencil marks: a page holds the marks of page / (kBlockNodes kMarkBytes) blocks.
    const std::size_t per_page = page / std::max<std::size_t>(1, kBlockNodes * kMarkBytes);
    for (std::size_t q = 0; q < mark_resident.size(); ++q) {
      if (mark_resident[q] == 0) continue;
      bool free = true;
      for (std::size_t c = q * per_page; c < std::min(count, (q + 1) * per_page) && free; ++c) {
        free = idle(c);
      }
      if (!free) continue;
      stencil_mark.release(q * page, page);
      mark_resident[q] = 0;
    }
  }
  /// Bytes of the node arrays backed by memory: the pages that overlap a block that may hold
  /// memory (what release_idle() has not returned), and of the stencil marks the pages that
  /// may hold memory (mark_resident: set for the pages of active blocks' marks, the only marks
  /// written, cleared when release_idle() returns a page; an upper bound, since a remap at the
  /// epoch's wrap returns them all without clearing it).
  /// Dense: the whole box (its pages are written as the material reaches them, and kept).
  [[nodiscard]] std::size_t committed_bytes() const {
    if (!sparse) return box_bytes();
    const auto mark_pages = static_cast<std::size_t>(
        std::count(mark_resident.begin(), mark_resident.end(), std::uint8_t{1}));
    return resident_pages() + mark_pages * PageBuffer::page_size();
  }
  /// Bytes the active blocks' nodes need (what a block-sparse store could not do without).
  [[nodiscard]] std::size_t active_bytes() const {
    return active_blocks.size() * kBlockNodes * (kNodeBytes + kMarkBytes);
  }
  /// Bytes of the node arrays' pages that overlap a block that may hold memory (sparse).
  [[nodiscard]] std::size_t resident_pages() const {
    const std::size_t page = PageBuffer::page_size();
    std::size_t pages = 0, next = 0;  // pages counted, and the first page not yet counted
    for (std::size_t b = 0; b < resident.size(); ++b) {
      if (resident[b] == 0) continue;
      const std::size_t first = std::max(next, b * kBlockBytes / page);
      const std::size_t last = ((b + 1) * kBlockBytes - 1) / page;
      if (last >= first) pages += last - first + 1;
      next = last + 1;
    }
    return pages * page;
  }
};

/// Weights of one particle over its grid stencil (S^D nodes). Built once per particle per pass.
template <int D, class Shape>
struct Stencil {
  static constexpr int S = Shape::support;
  Index<D> base;
  double w[D][S];
  double dw[D][S];      ///< already divided by h
  double dx[D][S];      ///< x_I - x_p per axis
  int offset[D][S];     ///< node (i, j, k) is offset[0][i] + offset[1][j] + offset[2][k]
  bool row_contiguous;  ///< are the nodes along the last axis adjacent in memory?

  Stencil(const Grid<D>& g, const Vec<D>& x, double half_width) {
    for (int d = 0; d < D; ++d) {
      const double xg = (x[d] - g.origin[d]) * g.inv_h;
      Shape::weights(xg, half_width, base[d], w[d], dw[d]);
      for (int k = 0; k < S; ++k) {
        dw[d][k] *= g.inv_h;
        dx[d][k] = (base[d] + k - xg) * g.h;
      }
      if (!g.sparse) {  // dense: a multiple of the stride (no table lookup in the hot loops)
        for (int k = 0; k < S; ++k) offset[d][k] = (base[d] + k) * g.local_stride[d];
        continue;
      }
      for (int k = 0; k < S; ++k) offset[d][k] = g.axis_offset(d, base[d] + k);
    }
    row_contiguous = offset[D - 1][S - 1] - offset[D - 1][0] == S - 1;
  }

  /// f(node, N_I(x_p), grad N_I(x_p), x_I - x_p) for every node of the stencil.
  template <class F>
  void for_each(const Grid<D>& /*g*/, F&& f) const {
    if constexpr (D == 1) {
      for (int i = 0; i < S; ++i) f(offset[0][i], w[0][i], Vec<1>(dw[0][i]), Vec<1>(dx[0][i]));
    } else if constexpr (D == 2) {
      for (int i = 0; i < S; ++i) {
        for (int j = 0; j < S; ++j) {
          const int node = offset[0][i] + offset[1][j];
          f(node, w[0][i] * w[1][j], Vec<2>(dw[0][i] * w[1][j], w[0][i] * dw[1][j]),
            Vec<2>(dx[0][i], dx[1][j]));
        }
      }
    } else {
      for (int i = 0; i < S; ++i) {
        for (int j = 0; j < S; ++j) {
          const double wij = w[0][i] * w[1][j];
          const double dwi_j = dw[0][i] * w[1][j];
          const double wi_dj = w[0][i] * dw[1][j];
          const int row = offset[0][i] + offset[1][j];
          for (int k = 0; k < S; ++k) {
            f(row + offset[2][k], wij * w[2][k],
              Vec<3>(dwi_j * w[2][k], wi_dj * w[2][k], wij * dw[2][k]),
              Vec<3>(dx[0][i], dx[1][j], dx[2][k]));
          }
        }
      }
    }
  }
};

}  // namespace mpm
