#pragma once
// State of one dual-grid wall inside the solver (DESIGN.md section 4): the boundary grid's nodal
// arrays, its Gamma nodes with their wall frames, and the multipliers that tie it to the standard
// grid, on Phi (Blending) or on Gamma (Enhanced velocity field).

#include <Eigen/LU>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <functional>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "mpm/boundary_package.hpp"
#include "mpm/node_array.hpp"
#include "mpm/scene.hpp"
#include "mpm/types.hpp"
#include "mpmgeom/locator.hpp"

namespace mpm {

/// Boundary-grid basis of one particle: values and physical gradients at its natural
/// coordinates (the isoparametric map of the cell).
template <int D>
struct AlphaStencil {
  int count = 0;
  int node[6] = {};
  double N[6] = {};
  Vec<D> dN[6];
};

/// How ldlt_solve() (sparse_pattern.hpp) shares the triangular solves of a factor between two
/// threads. Column j of L holds rows only among j's ancestors in the elimination tree, so two
/// disjoint subtrees can be solved at once: `side[0]`, `side[1]` are two sets of whole subtrees
/// (each side's columns in increasing order), `top` the columns above them (increasing), which
/// the forward solve takes after both sides and the backward solve before them. A column of a
/// side reaches the top only through rows beyond its subtree's root, `root[j]`; the second
/// side's updates of top rows go to a buffer (`top_slot[i]`: the row's place in it) that is
/// added after both sides: the same sums for any thread count. `parallel` is false where the
/// split would not pay (a small factor, or a tree that does not branch near its root).
struct SubtreeSplit {
  bool parallel = false;
  std::vector<int> side[2], top;
  std::vector<int> root, top_slot;
};

/// Splits the elimination tree of the unit lower factor `l` (Eigen's column storage, row indices
/// increasing in each column) for ldlt_solve() (SubtreeSplit).
SubtreeSplit split_subtrees(const Eigen::SparseMatrix<double>& l);

/// Runs of consecutive columns of a unit lower factor L that ldlt_solve() (sparse_pattern.hpp)
/// takes as one: in a run [first, end) each column's rows are the next column's with that
/// column added on top (a fundamental supernode: the run's triangle is dense and every column
/// shares the rows below the run). The solve then reads those rows' indices once for the run
/// and updates (forward) or reads (backward) them through a dense buffer, a contiguous stretch
/// of each column's values at a time, instead of row by row through the index for every column.
/// The floor benchmark's Phi coupling has 1,620 columns, 1,236 of them in 40 runs of 4 or more
/// (31 on average); Enhanced's contact system about 5,000 of 6,450 in 170 runs. A run lies in
/// one part of the split (SubtreeSplit): `all` covers every column, `side` and `top` the split's
/// parts, each in its columns' order.
struct ColumnRuns {
  std::vector<std::array<int, 2>> all, side[2], top;
  int most_below = 0;  ///< the most rows below one run of two or more columns
};

/// The runs of `l` (Eigen's column storage, row indices increasing in each column, the
/// diagonal not stored) in `split`'s parts (ColumnRuns).
ColumnRuns column_runs(const Eigen::SparseMatrix<double>& l, const SubtreeSplit& split);

/// Which values of L a solve with a SparseLdlt reads (ldlt_solve(), sparse_pattern.hpp).
enum class LdltValues {
  full,    ///< L as factorised: the solve is exact to round-off
  single,  ///< L rounded to single precision (SparseLdlt::round_to_single()): a preconditioner
  /// L's entries of at least SparseLdlt::kDropBelow of their row's scale, in single precision
  /// (SparseLdlt::dropped()): a cheaper preconditioner
  dropped
};

/// Eigen's sparse LDL^T, with read access to D (its vectorD() returns a copy: an allocation
/// per solve in ldlt_solve(), sparse_pattern.hpp), and the split of its elimination tree for
/// solves on two threads and the runs of its columns (ColumnRuns), made again after the first
/// factorisation of each new pattern (the tree and L's structure depend on the pattern only).
///
/// A solve that only preconditions (conjugate gradients against an earlier step's factor,
/// conjugate_refine()) may read L rounded to single precision: 8 bytes an entry with its row
/// index instead of 12. The floor benchmark's S has 261,001 entries in L, 3.1 MB in double that
/// stream from the shared cache at every pass and 2.1 MB in single, about what one core's
/// second-level cache holds: the mortar floor's solves 14-17% faster, the same passes
/// (docs/performance.md, 2026-12-06). Rounding L moves F^-1 S by about 1e-7 times S's
/// condition number; CG's residual is formed in double, so it still stops at 1e-10, in the same
/// passes wherever the factor's age moves F^-1 S more than that (the mortar floor: a first
/// correction of 3e-4 of lambda), one more a solve where it ages less (the one-way floor, no
/// slower for it). Only a solver made with LdltValues::single keeps the copy (the Phi
/// coupling's; Enhanced's, which refines by plain refinement, does not: its L has 1.33 M
/// entries on the floor, and rounding cost refinement passes, docs/performance.md 2026-12-04).
/// A solver made with LdltValues::single or LdltValues::dropped keeps L's dropped copy
/// (LdltValues::dropped, made by factorize()), which solves against an aged factor read once
/// the first exact solve with the factorisation has found it close (check_dropped(),
/// sparse_pattern.hpp): the Phi coupling's CG since 2026-12-07 (evening), Enhanced's
/// refinement since that night. Their passes are set by how far the matrix has moved, not by
/// L's small entries.
class SparseLdlt : public Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> {
  using Base = Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>;

 public:
  /// `kept`: LdltValues::single to keep L's single-precision copy and its dropped copy as well,
  /// LdltValues::dropped for the dropped copy alone.
  explicit SparseLdlt(LdltValues kept = LdltValues::full)
      : keeps_single_(kept == LdltValues::single), keeps_dropped_(kept != LdltValues::full) {}
  [[nodiscard]] const Eigen::VectorXd& diagonal() const { return m_diag; }
  [[nodiscard]] const SubtreeSplit& split() const { return split_; }
  [[nodiscard]] const ColumnRuns& runs() const { return runs_; }
  /// L's values in single precision, in L's order, once round_to_single() has filled them
  /// for the factorisation in hand (`rounded()`).
  [[nodiscard]] const std::vector<float>& single_values() const { return single_; }
  [[nodiscard]] bool rounded() const { return single_ready_; }
  /// Rounds L's values to single precision for LdltValues::single solves, once per
  /// factorisation (later calls return at once); no allocation (factorize() sized the copy).
  void round_to_single() {
    if (!keeps_single_) throw std::logic_error("SparseLdlt: made without a single-precision L");
    if (single_ready_) return;
    const auto& l = matrixL().nestedExpression();
    std::copy(l.valuePtr(), l.valuePtr() + l.nonZeros(), single_.begin());
    single_ready_ = true;
  }
  /// The dropped copy of L (LdltValues::dropped), made by factorize() for a solver that keeps
  /// a single-precision L: by columns, the entries l_ij (i > j) with |l_ij| (d_j / d_i)^1/2 of
  /// at least kDropBelow, i.e. of the factor L D^1/2's row i scaled by its diagonal. The
  /// Phi coupling's S (its multipliers' supports overlap along the surface) has most of its
  /// fill far below that: the floor benchmark's factor keeps 57,881 of its 261,001 entries,
  /// and a CG pass against an aged factor takes as many passes with the copy as with all of L
  /// (docs/performance.md, 2026-12-07, evening).
  static constexpr double kDropBelow = 1e-4;
  struct Dropped {
    std::vector<int> outer, inner;
    std::vector<float> value;
  };
  [[nodiscard]] const Dropped& dropped() const { return dropped_; }
  [[nodiscard]] bool keeps_dropped() const { return keeps_dropped_; }
  /// Whether solves against this factorisation once the matrix has moved (it only
  /// preconditions then) read the dropped copy: unchecked from each factorisation until
  /// check_dropped() (sparse_pattern.hpp) compares the copy's answer with an exact one;
  /// checkpoints save it, so that a resumed run reads the same values.
  enum class DroppedUse : std::uint8_t { unchecked, usable, unusable };
  [[nodiscard]] DroppedUse dropped_use() const { return dropped_use_; }
  void set_dropped_use(DroppedUse use) { dropped_use_ = use; }
  /// What a solve that only preconditions (the matrix has moved since) reads: the dropped copy
  /// where its check passed, `otherwise` (all of L, or its single-precision copy) elsewhere.
  [[nodiscard]] LdltValues aged_values(LdltValues otherwise) const {
    return dropped_use_ == DroppedUse::usable ? LdltValues::dropped : otherwise;
  }
  void compute(const Eigen::SparseMatrix<double>& a) {
    analyzePattern(a);
    factorize(a);
  }
  /// Whether analyzePattern() may keep the fill-reducing ordering in hand: Order::kept where
  /// a's unknowns are those of the matrix analysed last, in the same order (a matrix whose
  /// entries moved, came or went: refinement against an aged factorisation that failed, where
  /// the unknowns are those of the factorisation in hand by definition).
  enum class Order : std::uint8_t { fresh, kept };
  /// The fill-reducing ordering (Eigen's AMD) and the symbolic factorisation of a's pattern (a's
  /// lower triangle). With Order::kept, the ordering in hand is kept (only the symbolic step is
  /// taken) unless L would then have more than kReorderFill times the entries it had when that
  /// ordering was made for its own matrix: Eigen's AMD took 60-85 ms of the 250-280 ms an
  /// Enhanced floor factorisation took (docs/performance.md, 2026-12-07, late night), and the fill
  /// of a kept ordering grew 0-1.5% over the 20-40 steps between factorisations there.
  void analyzePattern(const Eigen::SparseMatrix<double>& a, Order order = Order::fresh);
  /// The symbolic factorisation of a's pattern in the ordering `inverse` (Eigen's P^-1: entry k
  /// the unknown eliminated k-th), which was made for a matrix whose L had `ordered_fill`
  /// entries: a checkpoint's factorisation made again as the run made it.
  void analyzePattern(const Eigen::SparseMatrix<double>& a, const std::vector<int>& inverse,
                      std::size_t ordered_fill);
  /// L's entries (below the diagonal) when the ordering in hand was made (analyzePattern()).
  [[nodiscard]] std::size_t ordered_fill() const { return ordered_fill_; }
  /// analyzePattern() calls that kept the ordering in hand (Order::kept and the fill test
  /// passed) so far.
  [[nodiscard]] std::size_t kept_orderings() const { return kept_orderings_; }
  static constexpr double kReorderFill = 1.05;
  void factorize(const Eigen::SparseMatrix<double>& a) {
    const auto start = std::chrono::steady_clock::now();
    Base::factorize(a);
    if (split_stale_ && info() == Eigen::Success) {
      split_ = split_subtrees(matrixL().nestedExpression());
      runs_ = column_runs(matrixL().nestedExpression(), split_);
      split_stale_ = false;
    }
    // Sized here, in the step that factorises (a later step's rounding allocates nothing).
    if (keeps_single_) {
      single_.resize(static_cast<std::size_t>(matrixL().nestedExpression().nonZeros()));
    }
    if (keeps_dropped_ && info() == Eigen::Success) drop_small();
    single_ready_ = false;
    dropped_use_ = DroppedUse::unchecked;
    ++factorizations_;
    numeric_seconds_ += since(start);
  }
  /// Wall-clock seconds spent so far in analyzePattern() (the fill-reducing ordering and the
  /// elimination tree) and in factorize() (the numeric factorisation and the solves' split).
  [[nodiscard]] double analysis_seconds() const { return analysis_seconds_; }
  /// factorize() calls so far: tells one factorisation from the next.
  [[nodiscard]] std::size_t factorizations() const { return factorizations_; }
  [[nodiscard]] double numeric_seconds() const { return numeric_seconds_; }

 private:
  static double since(std::chrono::steady_clock::time_point start) {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  }
  void drop_small() {
    const auto& l = matrixL().nestedExpression();
    const auto n = static_cast<std::size_t>(l.outerSize());
    dropped_.outer.assign(n + 1, 0);
    dropped_.inner.clear();
    dropped_.value.clear();
    root_.resize(n);  // |d_i|^1/2, one square root a row rather than two an entry
    for (std::size_t i = 0; i < n; ++i) {
      root_[i] = std::sqrt(std::abs(m_diag[static_cast<Eigen::Index>(i)]));
    }
    for (std::size_t j = 0; j < n; ++j) {
      const double root_j = root_[j];
      for (int p = l.outerIndexPtr()[j]; p < l.outerIndexPtr()[j + 1]; ++p) {
        const int i = l.innerIndexPtr()[p];
        if (i <= static_cast<int>(j)) continue;
        const double v = l.valuePtr()[p];
        // Kept unless small against row i's scale (a zero pivot keeps its row whole).
        if (!(std::abs(v) * root_j < kDropBelow * root_[static_cast<std::size_t>(i)])) {
          dropped_.inner.push_back(i);
          dropped_.value.push_back(static_cast<float>(v));
        }
      }
      dropped_.outer[j + 1] = static_cast<int>(dropped_.inner.size());
    }
  }
  SubtreeSplit split_;
  ColumnRuns runs_;
  Dropped dropped_;
  std::vector<float> single_;
  std::vector<double> root_;
  /// The symbolic factorisation of a's pattern in the ordering m_P; L's entries below the
  /// diagonal.
  std::size_t symbolic(const Eigen::SparseMatrix<double>& a);
  std::size_t ordered_fill_ = 0, kept_orderings_ = 0;
  bool keeps_single_ = false;
  bool keeps_dropped_ = false;
  DroppedUse dropped_use_ = DroppedUse::unchecked;
  bool split_stale_ = true;
  bool single_ready_ = false;
  double analysis_seconds_ = 0.0, numeric_seconds_ = 0.0;
  std::size_t factorizations_ = 0;
};

/// The inverse, through a factorisation F of an earlier matrix, of a matrix whose unknowns are
/// F's but for a few: some of F's unknowns gone and a few new ones (Enhanced's contact system
/// when a few multipliers come into contact or leave it: the floor benchmark's changes held 1 to
/// 8 of its 1,560 rows, and each factorised anew, about 100 ms, where the solves against the
/// factorisation in hand take about 1). With K the unknowns kept and Q the new ones, the matrix
///
///   A~ = [ F_KK  B ]      B, C: the new matrix's columns of Q (its rows of K, and of Q),
///        [ B^T   C ]
///
/// is inverted exactly: F_KK^-1 y as the solve of F x = y + E_R t with x_R = 0 for the gone
/// unknowns R (t = -(F^-1)_RR^-1 (F^-1 y)_R, through G = F^-1 E_R), then by blocks through the
/// Schur complement Z = C - B^T F_KK^-1 B. So A~ differs from the new matrix where F differs
/// from its own (the masses' drift since F was factorised), and refinement against A~^-1
/// converges as it would against F with unchanged unknowns. Setting up takes |R| + |Q| solves
/// with F and |Q| columns of the new matrix; each solve then one with F and dense products of
/// |R| + |Q| columns. Allocates only in prepare().
class BorderedFactor {
 public:
  /// `old_of[i]`: F's unknown that the new matrix's unknown i is, or -1 for a new one (each of
  /// F's at most once; std::logic_error if one is not F's); `column(j, out)` sets `out` to the new
  /// matrix's column j (its size); `values`: which values of L F's solves read (ldlt_solve()).
  /// Returns false where A~ is singular to working precision (the caller factorises the new matrix
  /// instead).
  bool prepare(const SparseLdlt& solver, LdltValues values, const std::vector<int>& old_of,
               const std::function<void(int, Eigen::VectorXd&)>& column);
  /// x = A~^-1 y (the new matrix's unknowns).
  void solve(const Eigen::VectorXd& y, Eigen::VectorXd& x);
  [[nodiscard]] std::size_t removed() const { return removed_.size(); }
  [[nodiscard]] std::size_t added() const { return added_.size(); }

 private:
  void reduced_solve();
  const SparseLdlt* solver_ = nullptr;
  LdltValues values_ = LdltValues::full;
  std::vector<int> old_of_, removed_, added_;
  Eigen::MatrixXd g_, b_, y_;  ///< F^-1 E_R; B and F_KK^-1 B in F's unknowns
  Eigen::PartialPivLU<Eigen::MatrixXd> h_, z_;
  Eigen::VectorXd s_, t_, tau_, solved_tau_, xq_, solved_xq_;
  std::vector<double> work_;
};

/// Scratch of product_into() (sparse_pattern.hpp), kept between calls, with the pattern of
/// the product it made last.
struct ProductWork {
  Eigen::SparseMatrix<double> lhs_rows;  ///< A^T
  std::vector<double> product, base, value;
  /// Per row of C: the column that last touched it (general pass), or its entry in the column
  /// at hand (pattern kept); the rows one column touches.
  std::vector<int> mark, touched;
  std::vector<char> reached;  ///< entries of the last pattern a term or X has reached
  Eigen::Index pattern_rows = -1;
  std::vector<int> c_outer, c_inner;  ///< the last product's pattern (empty: none yet)
};

/// Scratch of refined_solve() (sparse_pattern.hpp) for right-hand sides of type Rhs.
template <class Rhs>
struct SolveWork {
  Rhs residual, update;
  std::vector<double> work;  ///< ldlt_solve()'s
};

/// D components per node or multiplier, one row each, for the couplings' sparse products and
/// solves. Row-major, so that each entry of a sparse matrix updates (or reads) one row's D
/// values side by side: column-major, the products with R^A and R^alpha took twice as long (the
/// floor's mortar coupling 3.3-3.9 -> 1.5-1.7 ms a step in its products, docs/performance.md,
/// 2026-12-04). Eigen wants a one-column matrix column-major.
template <int D>
using NodeBlock =
    Eigen::Matrix<double, Eigen::Dynamic, D, D == 1 ? Eigen::ColMajor : Eigen::RowMajor>;

/// Contact state of one Gamma multiplier in Enhanced's active-set loop.
enum class Contact : unsigned char { off, normal, stick, slip };

/// One pass of Enhanced's active-set loop (enhanced_solve()) for one Gamma multiplier, given
/// this pass's solve: `total` its impulse (the held part and the friction `load`), `gap` the
/// velocity the coupled field has at it, `normal` the wall's normal into the material. `state`
/// becomes:
/// - off -> `on` (its state in contact) where a separable wall's gap closes (gap . n < 0),
///   unless the multiplier was released twice already in this step (`releases`): it then
///   stays off and `kept_released` is set. On rough contact one or two multipliers alternated
///   between pulling when held and closing their gap when released, each pass a new
///   factorisation, until the loop's passes ran out (docs/performance.md, 2026-12-05);
/// - held -> off where a separable wall pulls (total . n < 0); `releases` counts it and the
///   friction load is dropped;
/// - stick -> slip where the tangential impulse exceeds mu |total . n| (by more than 1e-9 of
///   it), the load then that impulse's direction capped at mu |total . n|;
/// - slip -> stick where the load reversed the sliding (the gap's tangential part along the
///   load); otherwise the load follows the new normal impulse (changed if by more than 1e-9).
/// Frictionless (mu 0) and sticky multipliers keep their held state. Returns whether the
/// state or the load changed (the loop solves again if any did).
template <int D>
bool update_contact(Contact& state, unsigned char& releases, Vec<D>& load, Contact on, double mu,
                    bool separable, const Vec<D>& normal, const Vec<D>& total, const Vec<D>& gap,
                    bool& kept_released) {
  kept_released = false;
  if (state == Contact::off) {
    if (separable && gap.dot(normal) < 0.0) {
      if (releases < 2) {
        state = on;
        return true;
      }
      kept_released = true;
    }
    return false;
  }
  const double jn = total.dot(normal);
  if (separable && jn < 0.0) {
    state = Contact::off;
    ++releases;
    load.setZero();
    return true;
  }
  if (mu <= 0.0) return false;
  const double limit = mu * std::abs(jn);
  if (state == Contact::stick) {
    const Vec<D> jt = total - jn * normal;
    if (jt.norm() > limit * (1.0 + 1e-9)) {
      state = Contact::slip;
      load = limit / jt.norm() * jt;
      return true;
    }
    return false;
  }
  const Vec<D> dir = load.normalized();
  const Vec<D> slide = gap - gap.dot(normal) * normal;
  if (slide.dot(dir) > 0.0) {
    state = Contact::stick;
    load.setZero();
    return true;
  }
  const Vec<D> updated = limit * dir;
  if ((updated - load).norm() > 1e-9 * (limit + 1e-300)) {
    load = updated;
    return true;
  }
  return false;
}

/// Per-step state of the Enhanced velocity field method (enhanced.cpp). Compact indices: the
/// standard-grid nodes the layer's particles reach ("near" rows), the free boundary-grid nodes
/// that carry an enhancement ("alpha" columns) and the Gamma multipliers in contact.
template <int D>
struct EnhancedState {
  std::vector<int> a_rows;                 ///< compact row -> standard-grid node
  NodeArray<int> a_row_of;                 ///< standard-grid node -> row (node_row())
  std::vector<int> alpha_cols;             ///< compact column -> boundary-grid node
  std::vector<int> alpha_col_of;           ///< boundary-grid node -> compact column, -1
  Eigen::VectorXd inv_mass;                ///< 1 / m^A of the near rows
  Eigen::VectorXd alpha_mass;              ///< lumped m^alpha of the columns
  Eigen::SparseMatrix<double> cross;       ///< m^{A,alpha}: near rows x alpha columns
  Eigen::SparseMatrix<double> schur;       ///< K = M^alpha - C^T M_A^-1 C (alpha columns)
  Eigen::SparseMatrix<double> gamma_grid;  ///< R^A on Gamma, all multipliers (grid node rows)
  Eigen::SparseMatrix<double> grid_r;      ///< R^A on Gamma: near rows x active multipliers
  Eigen::SparseMatrix<double> alpha_r;     ///< R^alpha on Gamma: alpha columns x multipliers
  Eigen::SparseMatrix<double> coupled_r;   ///< W = R^alpha - C^T M_A^-1 R^A
  Eigen::SparseMatrix<double> grid_rr;     ///< R^A^T M_A^-1 R^A
  std::vector<int> multipliers;            ///< active multiplier -> wall-coupling column
  std::vector<Vec<D>> normal;              ///< unit normal into the material, per multiplier
  std::vector<int> part;                   ///< part index, per multiplier
  Eigen::VectorXd integral;                ///< sum of the kept R^A entries (= integral S_mu)
  /// Both keep L's dropped copy, which their refinement reads once it is checked
  /// (refined_solve(), sparse_pattern.hpp).
  std::unique_ptr<SparseLdlt> schur_solver = std::make_unique<SparseLdlt>(LdltValues::dropped);
  std::unique_ptr<SparseLdlt> kkt_solver = std::make_unique<SparseLdlt>(LdltValues::dropped);
  std::size_t dropped_dependent = 0;  ///< alpha nodes dropped this step (near-dependent bases)
  std::size_t dropped_covered = 0;    ///< Gamma nodes the standard grid alone covers this step
  double min_mass_ratio = 1.0;        ///< smallest K_SS / m^alpha_S kept this step
  /// Since the run (or its resume) began: the active-set passes, the steps whose active set had
  /// not settled after the 30 passes allowed (the last pass's states then stand), and the times
  /// a multiplier released twice in a step was kept released though its gap closed.
  std::size_t active_set_passes = 0, unsettled_steps = 0, kept_released = 0;
  /// This step's contact system is prepared for the held rows `prepared_signature`: solved by
  /// refinement against the factorisation in hand (kkt_refine), through `bordered` where its
  /// rows are not the factorised ones (kkt_bordered), or factorised.
  bool kkt_ready = false;
  std::vector<int> prepared_signature;
  /// The contact system's solutions of the last two solves of the step's own velocities (not
  /// FLIP's old ones, nor MUSL's remap), [0] the last, with their held rows (signature) and
  /// enhancement nodes: refinement against an aged factorisation starts from 2 x_0 - x_1 where
  /// both are for the unknowns of the system in hand (enhanced_solve()). Checkpoints save them.
  std::array<Eigen::VectorXd, 2> recent_solution;
  std::array<std::vector<int>, 2> recent_signature, recent_columns;
  /// The held rows of the factorisation in hand: 4 * multiplier + contact state, per row.
  std::vector<int> kkt_signature;
  /// The factorisation in hand bordered for the unknowns (held rows, enhancement nodes) that
  /// came or went since (BorderedFactor), its map of unknowns, and the factorised rows' keys
  /// (signature, and which of a multiplier's rows) sorted.
  BorderedFactor bordered;
  bool kkt_bordered = false;
  /// Unknowns gone or new summed over the borderings of the factorisation in hand (the one
  /// kkt_solver->factorizations() called `bordered_factor`): past kBorderedBudget the next
  /// change factorises (enhanced_solve()). A checkpoint saves it.
  std::size_t bordered_rows = 0, bordered_factor = 0;
  std::vector<int> bordered_old_of;
  std::vector<std::pair<std::int64_t, int>> bordered_keys;
  Eigen::VectorXd bordered_unit;
  std::size_t kkt_pattern = 0;     ///< sparsity hash of the last analysed matrix
  std::size_t factorizations = 0;  ///< contact-system factorisations so far (for benchmarks)
  std::size_t refinements = 0;     ///< refinement passes against an earlier factorisation
  bool kkt_factored = false;       ///< kkt_solver holds a valid factorisation (maybe older)
  bool kkt_refine = false;         ///< this step's matrix is solved by refinement
  std::size_t schur_pattern = 0;   ///< sparsity hash of the factorised K
  bool schur_factored = false;     ///< schur_solver holds a valid factorisation (maybe older)
  bool schur_refine = false;       ///< this step's K is solved by refinement
  bool schur_ready = false;        ///< schur_solver prepared for this step's K (schur_refine)
  /// K, W and S_A (schur, coupled_r, grid_rr) are this step's: formed only to factorise a matrix
  /// (enhanced_solve()); refinement applies them through cross, grid_r and alpha_r.
  bool products_formed = false;
  Eigen::SparseMatrix<double> kkt_matrix;  ///< this step's contact matrix (full storage)
  /// The contact matrix is formed only to be factorised: refinement applies it from the factors
  /// of its blocks (C, R^A, R^alpha, the masses and the held directions), against the
  /// factorisation in hand while its unknowns are this step's: the held rows (kkt_signature)
  /// and these enhancement nodes (alpha_cols when it was factorised; saved in a checkpoint).
  std::vector<int> kkt_alpha_cols;
  bool kkt_formed = false;  ///< kkt_matrix is this step's, for prepared_signature
  double kkt_shift = 0.0;   ///< the held rows' diagonal shift (relative 1e-10 of S_A's largest)
  /// The matrices the two factorisations in hand are of (maybe an earlier step's): saved in a
  /// checkpoint and factorised again on restore, so a resumed run refines against the very
  /// factorisations the uninterrupted run has, and agrees with it bit for bit.
  Eigen::SparseMatrix<double> schur_base, kkt_base;
  /// Contact state per multiplier from the step's solve, reused by the MUSL remap.
  std::vector<unsigned char> state;
  /// Final contact state per wall multiplier (all of them, 0xFF: not active) of the last step:
  /// the next step's active set starts from it.
  std::vector<unsigned char> previous_state;

  // Scratch kept from step to step, so that a step whose solves reuse the factorisations in
  // hand allocates nothing (issue 9; test_allocation).
  using Block = NodeBlock<D>;
  std::vector<int> candidates, renumber;
  std::vector<double> candidate_diagonal, integral_list;
  std::vector<char> covered;
  std::vector<Eigen::Triplet<double>> grid_entries, alpha_entries, kkt_entries;
  /// The cross mass by groups of layer particles with the same stencils on both grids
  /// (enhanced_assemble()). A particle's key: its standard stencil's first node, its boundary
  /// cell's rank among the cells in the order of their node lists (cell_rank: equal lists, equal
  /// ranks), its place in the layer list; sorted, the groups are the runs of equal (first, cell).
  struct CrossKey {
    int first, cell, place;
    auto operator<=>(const CrossKey&) const = default;
  };
  std::vector<CrossKey> cross_order;
  std::vector<int> cell_rank;  ///< per boundary cell (setup_dual_walls())
  /// Per group g (cross_group_first[g] .. cross_group_first[g + 1] - 1 in cross_order) and node
  /// q of its standard stencil: the node's row (its grid node until the rows are numbered), and
  /// the terms sum_p m_p N^A_q N^alpha_k with the boundary-cell nodes k
  /// (cross_sum[(g * kCellNodes + k) * stencil + q], written where node q has a term with k).
  std::vector<int> cross_group_first, cross_row;
  std::vector<double> cross_sum;
  /// Per group g and boundary-cell node k: the stencil nodes q with a term (bit q), at
  /// cross_mask[g * kCellNodes + k].
  std::vector<std::uint32_t> cross_mask;
  /// Per candidate column: its (group, k) pairs in group order (cross_pairs from
  /// cross_pair_first[c], as g * kCellNodes + k), where its merged entries go in cross_slab (at
  /// most as many as its terms: from cross_slab_first[c]) and how many there are.
  std::vector<int> cross_pair_first, cross_pairs, cross_slab_first, cross_count;
  std::vector<int> cross_slab_row;
  std::vector<double> cross_slab_value;
  /// A thread's accumulator of one column (dense over the rows, reset after each column), one
  /// per thread slot of the task arena (tbb::this_task_arena::current_thread_index()), sized
  /// before the columns' loop: the loop allocates nothing.
  struct CrossColumn {
    std::vector<double> sum;
    std::vector<char> held;
    std::vector<int> rows;
  };
  std::vector<CrossColumn> cross_column;
  /// assign_by_columns()' and product_into()'s scratch: one per matrix enhanced_assemble()
  /// forms at the same time as another (R^A and R^alpha; K, W and R^A^T M_A^-1 R^A).
  std::vector<int> assembly_work[2];
  Eigen::SparseMatrix<double> cross_candidates, minv_cross;
  Eigen::VectorXd grid_rr_diagonal;  ///< S_A's diagonal (its largest entry sets kkt_shift)
  ProductWork product_work[3];
  Block pa, ps, vs, vna, impulse, load, pa_load, ps_load, minv_pa, rhs_alpha, rt_minv_pa, gap;
  Block apply_v, apply_y, apply_j, apply_t, apply_u, apply_rj;  ///< the contact matrix by blocks
  std::vector<Contact> contact, on_contact;
  std::vector<unsigned char> releases;  ///< per multiplier: times released in this step's loop
  std::vector<double> friction;
  std::vector<std::pair<int, Vec<D>>> rows;  ///< held directions: (multiplier, direction)
  std::vector<int> signature, row_first;
  Eigen::VectorXd rhs, solution;
  /// Each held row's velocity per unit impulse, |M_A^-1 R^A n| (refinement's measure of x).
  Eigen::VectorXd impulse_weight;
  SolveWork<Block> schur_work;
  SolveWork<Eigen::VectorXd> kkt_work;
};

template <int D>
struct DualWall {
  /// Nodes of a layer cell in D dimensions (segment, quadrilateral, wedge).
  static constexpr int kCellNodes = 2 * D;
  const DualWallSpec* spec = nullptr;
  const mpmgeom::BoundaryGrid* layer = nullptr;
  std::unique_ptr<mpmgeom::LayerLocator> locator;
  /// Which standard-grid cells the layer meets, and where in them (locate_in_layers() asks the
  /// locator only about particles that may be in it).
  mpmgeom::LayerCellFilter cell_filter;
  /// Each layer cell's nodes, a cell's together (`layer->cells` is column-major: one cache line
  /// a node), for alpha_stencil().
  std::vector<std::array<int, kCellNodes>> cell_nodes;

  // Boundary-grid nodal arrays (same roles as in Grid<D>).
  std::vector<Vec<D>> position;
  std::vector<double> mass;
  std::vector<Vec<D>> momentum, force, velocity, velocity_new;
  std::vector<Vec<D>> momentum_new;  ///< Enhanced: p + dt f, the right-hand side of v^{n+1}
  /// MUSL remap: the mass centroid of the particles each node's remapped velocity comes from
  /// (where that velocity is the particles', layer_affine() in dual_grid.cpp).
  std::vector<Vec<D>> centroid;

  // Gamma: nodes on the wall, their unit normal into the material, and the part they report to.
  std::vector<int> wall_nodes;
  std::vector<int> wall_index_of_node;  ///< boundary node -> index in wall_nodes, -1 off Gamma
  std::vector<Vec<D>> wall_normal;
  std::vector<int> wall_node_part;
  /// Gamma nodes where wall facets meet at a concave corner or crease (the wall bends towards
  /// the material): corner_normals[corner_first[i] .. corner_first[i + 1]) are the distinct unit
  /// normals of the facets at wall node i, and the node may enter none of them (its own normal,
  /// their average, would let it slide into one). Empty for every other node.
  std::vector<int> corner_first;
  std::vector<Vec<D>> corner_normals;
  std::vector<int> corner_part;  ///< the part of the (first) facet with each corner normal
  /// Boundary node n's index in wall_nodes if it is on Gamma with a single facet normal
  /// (wall_normal; not a corner), else -1.
  [[nodiscard]] int flat_wall_index(std::size_t n) const {
    const int wi = wall_index_of_node[n];
    if (wi < 0) return -1;
    const auto wu = static_cast<std::size_t>(wi);
    return corner_first[wu + 1] == corner_first[wu] ? wi : -1;
  }
  /// Per corner normal, as touch_gap per node: the material's gap to that facet near the node.
  std::vector<double> corner_gap;
  /// Per boundary node (Gamma nodes only): min over the layer particles lying over its share of
  /// the facet of the distance of the particle's near edge from the wall along the node's
  /// normal, less the touch tolerance; the node is in contact only when it is <= 0 (separable
  /// walls). +inf where no particle.
  std::vector<double> touch_gap;
  /// Per layer cell: how far along the wall from a Gamma node of the cell a particle counts as
  /// lying over that node (the node's share of the facet, before the particle's half-size).
  std::vector<double> touch_window;
  int impulse_offset = 0;  ///< index of this wall's first part in the solver's wall impulses

  // Phi coupling: R^A (standard-grid nodes x multipliers) and R^alpha (boundary nodes x
  // multipliers), the integral of each multiplier basis, and the per-step workspace.
  Eigen::SparseMatrix<double> grid_coupling;
  Eigen::SparseMatrix<double> boundary_coupling;
  Eigen::VectorXd multiplier_integral;
  /// The Phi nodes of multiplier mu: multiplier_nodes[multiplier_first[mu] ..
  /// multiplier_first[mu + 1]) (one, its own node, unless the wall's "multiplier_radius"
  /// aggregates them: aggregate_multipliers()).
  std::vector<int> multiplier_first, multiplier_nodes;
  std::vector<int> multiplier_of_node;   ///< boundary node -> its multiplier, -1 off Phi
  std::vector<int> carried_multipliers;  ///< this step's with a Phi node that carries mass
  std::vector<int> active_multipliers;   ///< this step's multipliers that constrain something
  /// Kept rows (compacted: row k is node grid_rows[k] / layer_rows[k]) and rescaled columns, so
  /// the per-step work scales with the interface, not with the whole grid.
  Eigen::SparseMatrix<double> grid_active, boundary_active;
  /// Their transposes (column r: row r's entries), for the coupling's products by rows on
  /// both cores (layer_couple()); made again after grid_active and boundary_active change.
  Eigen::SparseMatrix<double> grid_active_t, boundary_active_t;
  bool transposes_current = false;
  std::vector<int> grid_rows, layer_rows;
  /// Inverses of grid_rows (node_row(): valid where grid_rows points back; page-backed, so a
  /// wall on a sparse grid holds memory only near its rows) and of layer_rows (-1: not a row
  /// this step), sized to the grids.
  NodeArray<int> grid_row_of;
  std::vector<int> layer_row_of;
  /// What the coupling in hand (grid_active, boundary_active and their rows) was assembled
  /// from, recorded when a step assembled the same one as the step before (layer_couple()):
  /// the carried multipliers, and the nodes of their supports on either grid with whether
  /// each carried mass above the coupling threshold (1) or not (0). While all of these hold,
  /// a step's assembly would give the same rows and entries, and is skipped. The marks are
  /// scratch for collecting each node once (all 0 between steps; page-backed on the grid).
  bool support_recorded = false;
  std::size_t kept_assemblies = 0;  ///< steps that kept the coupling in hand this way
  std::vector<int> recorded_carried;
  std::vector<int> support_grid_nodes, support_layer_nodes;
  std::vector<std::uint8_t> support_grid_above, support_layer_above;
  NodeArray<std::uint8_t> support_grid_mark;
  std::vector<std::uint8_t> support_layer_mark;
  /// The Schur complement S = R^A^T M_A^-1 R^A (+ R^alpha^T M_alpha^-1 R^alpha) + shift I on
  /// the active multipliers is kept as its factors (this step's inverse masses of the kept rows
  /// and the shift); `schur` holds a factorisation (held by pointer: Eigen's solvers cannot be
  /// moved) of `schur_base`, which may be an earlier step's S of the same active multipliers
  /// (`factored_structure`, their hash): the masses change a little from step to step, so it
  /// then preconditions conjugate gradients on S. A checkpoint saves `schur_base` and
  /// `factored_structure`. Only its lower triangle is S (all the factorisation reads):
  /// factorise_schur() leaves out the upper entries of its last columns.
  Eigen::VectorXd inv_grid_mass, inv_layer_mass;
  double schur_shift = 0.0;
  Eigen::SparseMatrix<double> schur_base;
  std::unique_ptr<SparseLdlt> schur = std::make_unique<SparseLdlt>(LdltValues::single);
  std::size_t pattern_hash = 0;        ///< sparsity of the last factorised S: reuse its ordering
  std::size_t factored_structure = 0;  ///< active multipliers' hash when `schur_base` was formed
  bool schur_factored = false;         ///< `schur` holds a valid factorisation (maybe older)
  bool schur_refine = false;           ///< this step's S is solved by refinement
  /// After a refinement that failed, steps to factorise without trying (refine_wait), and how
  /// many the next failure waits (0 after a success, then 1, doubled per failure up to 64).
  int refine_wait = 0, refine_backoff = 0;
  std::size_t factorizations = 0;  ///< Schur factorisations so far (for benchmarks)
  std::size_t refinements = 0;     ///< refinement passes against an earlier factorisation
  std::size_t reshapes = 0;        ///< steps whose kept rows changed (CouplingWork::reshaped_steps)
  /// Wall-clock seconds of the coupling's assembly (the active coupling and S, or Enhanced's
  /// blocks) and of its solves (refinement included), both without the factorisations made
  /// inside them, which the wall's solvers time themselves (SparseLdlt; CouplingWork).
  double assembly_seconds = 0.0, solve_seconds = 0.0;
  /// The coupling's scratch, kept from step to step so that a step that neither factorises nor
  /// joins other nodes allocates nothing (issue 9): the active coupling's entries, S's diagonal,
  /// and the solve's blocks (one row per kept row or active multiplier, one column per
  /// component; `search` and `search_product` are conjugate_refine()'s).
  std::vector<Eigen::Triplet<double>> grid_entries, layer_entries;
  /// The step before's rows and entries (layer_couple() keeps R^A and R^alpha when this step's
  /// are the same).
  std::vector<int> kept_grid_rows, kept_layer_rows;
  std::vector<Eigen::Triplet<double>> kept_grid_entries, kept_layer_entries;
  std::vector<int> assembly_work;
  Eigen::VectorXd schur_diagonal;
  NodeBlock<D> grid_block, layer_block, gap, lambda, residual, update, search, search_product;
  std::vector<double> solve_work;  ///< ldlt_solve()'s
  /// The multipliers the last solve of each kind found (0: the new velocities, 1: the old ones
  /// FLIP differences against, 2: MUSL's remap) and the hash of the active multipliers they are
  /// for (factored_structure then), and those of the solve of the kind before it (`earlier_`):
  /// CG against an aged factorisation starts from them, extrapolated, when the multipliers are
  /// the same (layer_couple()). Checkpoints save both.
  std::array<NodeBlock<D>, 3> last_lambda, earlier_lambda;
  std::array<std::size_t, 3> last_structure{}, earlier_structure{};
  double min_cell_size = 0.0;  ///< for the CFL limit
  /// Each boundary node's (cell, slot) pairs: node_cells[node_cell_first[n] ..
  /// node_cell_first[n + 1]), coded as cell times the nodes per cell plus the slot, cells in
  /// increasing order (setup_dual_walls()).
  std::vector<int> node_cell_first, node_cells;
  /// This step's layer particles by cell (layer_scatter()'s counting sort, which keeps the layer
  /// list's order within a cell): cell c holds the places cell_first[c] .. cell_first[c + 1],
  /// and cell_members[place] is the particle's place in the layer list. cell_cursor and
  /// node_reached are the sort's scratch (node_reached zero between sorts).
  std::vector<int> cell_first, cell_cursor, cell_members;
  std::vector<std::uint8_t> node_reached;
  /// The boundary nodes this step's layer particles reach, in increasing order (the only nodes
  /// whose arrays hold anything this step): those of the occupied cells.
  std::vector<int> scatter_nodes;
  /// Each (particle, stencil slot) pair's terms at slot * (layer particles) + place
  /// (layer_scatter() forms them particle by particle, then sums them node by node over the
  /// cells around it, a cell's particles' terms of one slot side by side: with a particle's
  /// slots side by side instead, each term a node read was a stride of six apart, the sums'
  /// loads most of the node pass): mass, momentum and force, or (the MUSL remap) momentum and
  /// the centroid's.
  std::vector<std::array<double, 1 + 2 * D>> scatter_terms;
  /// The terms of the pair (stencil slot `slot`, particle at `place` in the cell order).
  std::array<double, 1 + 2 * D>& scatter_term(int slot, std::size_t place) {
    return scatter_terms[static_cast<std::size_t>(slot) * cell_members.size() + place];
  }
  /// Separable walls: each pair's touch gap at the same place as its terms (layer_scatter():
  /// the particle's gap to the wall at the slot's node where the particle lies over the node's
  /// facet, +infinity elsewhere; a node's touch_gap is the least over its pairs). Not formed for
  /// corner nodes, whose gaps go per facet (corner_gap).
  std::vector<double> touch_terms;
  std::size_t layer_particles = 0;
  bool enhanced = false;  ///< superposed field (every particle also on the standard grid)
  EnhancedState<D> enh;
};

}  // namespace mpm
