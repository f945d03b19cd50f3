// The explicit MPM step on the standard grid (USL / MUSL, PIC-FLIP / APIC).

#include "mpm/solver.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <numeric>
#include <sstream>
#include <stdexcept>

#include <tbb/blocked_range.h>
#include <tbb/combinable.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_reduce.h>
#include <tbb/task_group.h>

#include "sparse_pattern.hpp"

namespace mpm {
namespace {

template <int D>
Vec<D> to_vec(const Eigen::VectorXd& v) {
  return v.head<D>();
}

template <int D>
bool inside(const BodySpec& body, const Vec<D>& x) {
  if (body.shape == BodySpec::Shape::box) {
    return (x.array() >= to_vec<D>(body.min).array()).all() &&
           (x.array() <= to_vec<D>(body.max).array()).all();
  }
  return (x - to_vec<D>(body.center)).squaredNorm() <= body.radius * body.radius;
}

template <int D>
std::string format_vec(const Vec<D>& v) {
  std::ostringstream s;
  s.precision(6);
  s << "(";
  for (int d = 0; d < D; ++d) s << (d ? ", " : "") << v[d];
  s << ")";
  return s.str();
}

}  // namespace

template <int D>
Solver<D>::Solver(const Scene& scene) : scene_(scene) {
  const double h = scene.spacing;
  Index<D> cells;
  for (int d = 0; d < D; ++d) {
    cells[d] = static_cast<int>(std::lround((scene.box_max[d] - scene.box_min[d]) / h));
  }
  grid.resize(to_vec<D>(scene.box_min) - Vec<D>::Constant(pad * h), h,
              cells + Index<D>::Constant(1 + 2 * pad));
  gravity_ = to_vec<D>(scene.gravity);
  for (const auto& body : scene.bodies) {
    body_acceleration_.push_back(gravity_ + to_vec<D>(body.body_force));
  }
  fill_bodies();
  choose_grid_storage();

  const double mean_mass =
      particles.size() ? std::accumulate(particles.mass.begin(), particles.mass.end(), 0.0) /
                             static_cast<double>(particles.size())
                       : 0.0;
  mass_threshold_ = scene.mass_threshold * mean_mass;
  coupling_threshold_ = std::max(mass_threshold_, scene.coupling_mass_threshold * mean_mass);

  // Nodes on the wall plane and the ghost nodes beyond it carry the wall condition.
  for (const auto& wall : scene.walls) {
    const int a = wall.axis;
    const int lo = wall.side < 0 ? 0 : pad + cells[a];
    const int hi = wall.side < 0 ? pad : grid.nodes[a] - 1;
    const int wall_index = wall.side < 0 ? pad : pad + cells[a];
    std::vector<int> nodes;
    std::vector<std::pair<int, int>> ghosts;
    for (int n = 0; n < static_cast<int>(grid.size()); ++n) {
      Index<D> i = grid.multi(n);
      if (!grid.in_box(i)) continue;
      if (i[a] < lo || i[a] > hi) continue;
      if (i[a] == wall_index || wall.contact.separable) {
        nodes.push_back(n);
      } else {
        i[a] = 2 * wall_index - i[a];
        ghosts.emplace_back(n, grid.linear(i));
      }
    }
    // Grouped by grid block, so that a step visits only the blocks it has active.
    auto by_block = [&](auto& list, auto node_of) {
      std::stable_sort(list.begin(), list.end(), [&](const auto& x, const auto& y) {
        return grid.block_of(node_of(x)) < grid.block_of(node_of(y));
      });
      std::vector<BlockRun> runs;
      for (int k = 0; k < static_cast<int>(list.size()); ++k) {
        const int block = grid.block_of(node_of(list[static_cast<std::size_t>(k)]));
        if (runs.empty() || runs.back().block != block) runs.push_back({block, k, k});
        runs.back().end = k + 1;
      }
      return runs;
    };
    wall_node_runs_.push_back(by_block(nodes, [](int n) { return n; }));
    wall_ghost_runs_.push_back(
        by_block(ghosts, [](const std::pair<int, int>& g) { return g.first; }));
    wall_nodes_.push_back(std::move(nodes));
    wall_ghosts_.push_back(std::move(ghosts));
  }
  wall_impulse_.assign(scene.walls.size(), Eigen::Vector3d::Zero());
  setup_dual_walls();
  // What stable_dt() needs of the scene is fixed once the walls are set up. Boundary-grid cells
  // may be smaller than the standard grid's. With APIC their linear basis takes C_p = grad v at
  // full weight from nodes the particle barely reaches; the incline and free-flight tests
  // (test_blending) show that stays stable only at about half the CFL number of the cell, so
  // the layer's cell size counts half there. So it does under USL and MLS for a Blending wall,
  // whose layer particles take their strain rate from v^{n+1} on that basis (with PIC and FLIP
  // the incline block diverged at the full cell, docs/blending.md).
  const bool apic = scene.transfer == Transfer::apic;
  const bool usl = scene.update != UpdateScheme::musl;
  step_size_ = grid.h;
  for (const auto& w : dual_) {
    const double layer_factor = apic || (usl && !w.enhanced) ? 0.5 : 1.0;
    step_size_ = std::min(step_size_, layer_factor * w.min_cell_size);
  }
  wave_speed_ = max_wave_speed(scene);
  viscous_dt_ = viscous_dt_limit(scene, step_size_);
  for (std::size_t p = 0; p < particles.size(); ++p) {
    max_speed_ = std::max(max_speed_, particles.velocity[p].norm());
  }
}

template <int D>
void Solver<D>::choose_grid_storage() {
  bool sparse = scene_.grid_storage == GridStorage::sparse;
  const bool automatic = scene_.grid_storage == GridStorage::automatic;
  if (automatic) {
    // The blocks the bodies reach (the grid's own marking, on the dense grid just made).
    grid.begin_marking();
    for (const Vec<D>& x : particles.position) grid.mark(x);
    grid.finish_marking();
    sparse = 2 * grid.active_blocks.size() < grid.block_active.size();
  }
  const Index<D> nodes = grid.nodes;
  try {
    grid.resize(grid.origin, grid.h, nodes, sparse);
  } catch (const std::runtime_error&) {  // beyond the sparse layout's index range
    if (!automatic) throw;
    grid.resize(grid.origin, grid.h, nodes, false);
  }
}

template <int D>
void Solver<D>::fill_bodies() {
  // Particles sit at the centres of the ppc^D sub-cells of every grid cell inside the body.
  const double h = scene_.spacing;
  struct Seed {
    Vec<D> x;
    int body;
    double volume;
  };
  std::vector<Seed> seeds;
  for (std::size_t b = 0; b < scene_.bodies.size(); ++b) {
    const BodySpec& body = scene_.bodies[b];
    const int n = body.particles_per_cell;
    if (body.own_lattice) {
      // A lattice aligned with the box's own edges, about h/n apart, filling it exactly.
      const Vec<D> extent = to_vec<D>(body.max) - to_vec<D>(body.min);
      const Vec<D> centre = 0.5 * (to_vec<D>(body.max) + to_vec<D>(body.min));
      Index<D> count;
      for (int d = 0; d < D; ++d) {
        count[d] = std::max(1, static_cast<int>(std::lround(extent[d] / (h / n))));
      }
      const long total = count.template cast<long>().prod();
      const double volume = extent.prod() / static_cast<double>(total);
      const Mat<D> R = body.rotation.topLeftCorner<D, D>();
      for (long k = 0; k < total; ++k) {
        long rest = k;
        Vec<D> local;
        for (int d = D - 1; d >= 0; --d) {
          const long i = rest % count[d];
          rest /= count[d];
          local[d] = (static_cast<double>(i) + 0.5) * extent[d] / count[d] - 0.5 * extent[d];
        }
        seeds.push_back({centre + R * local, static_cast<int>(b), volume});
      }
      continue;
    }
    if (body.shape == BodySpec::Shape::mesh) {
      if constexpr (D == 3) {
        for (Eigen::Index i = 0; i < body.points.rows(); ++i) {
          seeds.push_back(
              {body.points.row(i).transpose(), static_cast<int>(b), std::pow(h / n, D)});
        }
      }
      continue;
    }
    Vec<D> lo, hi;
    if (body.shape == BodySpec::Shape::box) {
      lo = to_vec<D>(body.min);
      hi = to_vec<D>(body.max);
    } else {
      lo = to_vec<D>(body.center).array() - body.radius;
      hi = to_vec<D>(body.center).array() + body.radius;
    }
    Index<D> first, count;
    for (int d = 0; d < D; ++d) {
      first[d] = static_cast<int>(std::floor((lo[d] - scene_.box_min[d]) / h * n));
      const int last = static_cast<int>(std::ceil((hi[d] - scene_.box_min[d]) / h * n));
      count[d] = std::max(0, last - first[d]);
    }
    const long total = count.template cast<long>().prod();
    for (long k = 0; k < total; ++k) {
      long rest = k;
      Vec<D> x;
      for (int d = D - 1; d >= 0; --d) {
        const long i = first[d] + rest % count[d];
        rest /= count[d];
        x[d] = scene_.box_min[d] + (static_cast<double>(i) + 0.5) * h / n;
      }
      if (inside<D>(body, x)) {
        seeds.push_back({x, static_cast<int>(b), std::pow(h / n, D)});
      }
    }
  }
  // Group by material so the constitutive update is dispatched once per group.
  std::stable_sort(seeds.begin(), seeds.end(), [&](const Seed& a, const Seed& b) {
    return scene_.bodies[a.body].material < scene_.bodies[b.body].material;
  });
  particles.resize(seeds.size());
  for (std::size_t p = 0; p < seeds.size(); ++p) {
    const BodySpec& body = scene_.bodies[seeds[p].body];
    const int n = body.particles_per_cell;
    const double volume = seeds[p].volume;
    particles.position[p] = seeds[p].x;
    particles.velocity[p] = to_vec<D>(body.velocity);
    if (body.velocity_sine) {
      const auto& sine = *body.velocity_sine;
      particles.velocity[p] += to_vec<D>(sine.amplitude) *
                               std::sin(sine.wavenumber * (seeds[p].x[sine.axis] - sine.origin));
    }
    particles.mass[p] = density(scene_.materials[body.material].model) * volume;
    particles.volume0[p] = volume;
    particles.half_width[p] = 0.5 / n;
    particles.material[p] = body.material;
    particles.body[p] = seeds[p].body;
  }
  // Only FLIP keeps a velocity other than the gathered one, whose step is the displacement.
  const bool flip = scene_.transfer == Transfer::flip && scene_.flip_blend > 0.0;
  particles.displacement.assign(flip ? seeds.size() : 0, Vec<D>::Zero());
  groups_.clear();
  for (std::size_t m = 0; m < scene_.materials.size(); ++m) {
    const auto lo =
        std::lower_bound(particles.material.begin(), particles.material.end(), static_cast<int>(m));
    const auto hi = std::upper_bound(lo, particles.material.end(), static_cast<int>(m));
    if (lo != hi) {
      groups_.emplace_back(lo - particles.material.begin(), hi - particles.material.begin());
    }
  }
}

template <int D>
double Solver<D>::stable_dt(double cfl) const {
  return cfl * std::min(step_size_ / (wave_speed_ + max_speed_), viscous_dt_);
}

template <int D>
void Solver<D>::step(double dt) {
  lap_start_ = std::chrono::steady_clock::now();
  particles_to_grid(dt);
  update_grid(dt);
  lap(&PhaseTimes::grid_update);
  apply_walls();
  lap(&PhaseTimes::walls);
  grid_to_particles(dt);
}

// Counting sort of particle indices by slab (slab_width cells along axis 0). O(N), no
// allocation once the buffers have grown. Fixed chunks of particles (not one per thread) count
// their particles per slab side by side, and each chunk then places its particles after the
// earlier chunks' ones of the same slab: within a slab the particles stay in index order, as a
// serial counting sort leaves them, whatever the thread count.
template <int D>
void Solver<D>::bin_particles_into_slabs() {
  const auto& P = particles;
  const int slabs = grid.nodes[0] / slab_width + 2;
  const auto per_chunk = static_cast<std::size_t>(slabs);
  constexpr std::size_t kChunk = 16384;
  const std::size_t n = P.size(), chunks = std::max<std::size_t>(1, (n + kChunk - 1) / kChunk);
  slab_count_.assign(chunks * per_chunk, 0);
  slab_of_.resize(n);
  slab_order_.resize(n);
  tbb::parallel_for(std::size_t{0}, chunks, [&](std::size_t c) {
    int* count = &slab_count_[c * per_chunk];
    for (std::size_t p = c * kChunk; p < std::min(n, (c + 1) * kChunk); ++p) {
      const double xg = (P.position[p][0] - grid.origin[0]) * grid.inv_h;
      const int slab = std::clamp(static_cast<int>(std::floor(xg / slab_width)), 0, slabs - 1);
      slab_of_[p] = slab;
      ++count[slab];
    }
  });
  // Each chunk's count becomes its first place in the slab.
  slab_start_.assign(per_chunk + 1, 0);
  int next = 0;
  for (std::size_t slab = 0; slab < per_chunk; ++slab) {
    slab_start_[slab] = next;
    for (std::size_t c = 0; c < chunks; ++c) {
      int& count = slab_count_[c * per_chunk + slab];
      const int here = count;
      count = next;
      next += here;
    }
  }
  slab_start_[per_chunk] = next;
  tbb::parallel_for(std::size_t{0}, chunks, [&](std::size_t c) {
    int* place = &slab_count_[c * per_chunk];
    for (std::size_t p = c * kChunk; p < std::min(n, (c + 1) * kChunk); ++p) {
      slab_order_[static_cast<std::size_t>(place[slab_of_[p]]++)] = static_cast<int>(p);
    }
  });
}

// One particle's share of the 3D grid, the sums factorised along the axes (N = w_i w_j w_k: the
// terms along the last axis are formed once per particle, a row of S nodes scales them):
// momentum N m (v + C (x_I - x_p)) and, with `body_force` (m b) and
// `stress` (-V sigma), mass N m and force N m b - V sigma grad N. With `mls` the force is
// MLS-MPM's, and with `fold` it goes into the momentum as dt f (see scatter()).
template <int D>
template <class Shape>
void Solver<D>::scatter_factorised(const Stencil<D, Shape>& st, double m, const double (&v)[D],
                                   const double (&C)[D][D], const double (*body_force)[D],
                                   const double (*stress)[D][D], bool mls, bool fold, double dt) {
  static_assert(D == 3);
  constexpr int S = Shape::support;
  const auto& w = st.w;
  const auto& dw = st.dw;
  const auto& dx = st.dx;
  // Along the last axis a row's S nodes are adjacent in memory (always in the dense layout; in
  // the sparse one unless the row crosses a block): their D S momentum (force) components are
  // then updated as one vector.
  static_assert(sizeof(Vec<3>) == 3 * sizeof(double), "grid vectors must be packed");
  static constexpr int R = 3 * S;  // static: the lambda below uses it without a capture
  // The force's weights per axis: grad N = (g_0 w_1 w_2, w_0 g_1 w_2, w_0 w_1 g_2) with g = dw;
  // MLS-MPM (Hu et al. 2018) replaces grad N by N D^-1 (x_I - x_p), so g = w dx (the stress
  // comes scaled by D^-1 = 4 / h^2).
  double g[3][S];
  for (int a = 0; a < 3; ++a) {
    for (int k = 0; k < S; ++k) g[a][k] = mls ? w[a][k] * dx[a][k] : dw[a][k];
  }
  double mv[3], mc[3][3];
  for (int a = 0; a < 3; ++a) {
    mv[a] = m * v[a];
    for (int b = 0; b < 3; ++b) mc[a][b] = m * C[a][b];
  }
  // With `fold` (MLS), dt f_I = dt N (m b - V sigma D^-1 (x_I - x_p)) has the momentum's form: it
  // joins the particle's m v and m C once, and the rows add nothing for it. (The grad N force
  // folded into the momentum rows as three more terms saved about 1% of a step: not done,
  // docs/performance.md.)
  fold = fold && mls && body_force != nullptr;
  if (fold) {
    for (int a = 0; a < 3; ++a) {
      mv[a] += dt * (*body_force)[a];
      for (int b = 0; b < 3; ++b) mc[a][b] += dt * (*stress)[a][b];
    }
  }
  const bool separate_force = body_force != nullptr && !fold;
  // A row's values (node k, component a at 3k + a) are the sums of a few per-particle vectors
  // scaled by the row's weights, formed here once per particle with the last axis's weights in
  // them (per row, the scalings alone: no per-row coefficients to spread over the components):
  //   momentum (i, j) = w_0i w_1j (P + dx_0i U + dx_1j V),
  //     P = w_2k (m v + m C_2 dx_2k), U = w_2k m C_0, V = w_2k m C_1 (C_b: column b of C);
  //   force (i, j) = w_0i w_1j F + g_0i w_1j G + w_0i g_1j H,
  //     F = w_2k m b + g_2k s_2, G = w_2k s_0, H = w_2k s_1 (s_b: column b of -V sigma).
  double P[R], U[R], V[R], F[R], G[R], H[R];
  for (int c = 0; c < R; ++c) {
    const int a = c % 3, k = c / 3;
    const double wk = w[2][k];
    P[c] = wk * (mv[a] + mc[a][2] * dx[2][k]);
    U[c] = wk * mc[a][0];
    V[c] = wk * mc[a][1];
    if (separate_force) {
      const auto& vs = *stress;
      F[c] = wk * (*body_force)[a] + g[2][k] * vs[a][2];
      G[c] = wk * vs[a][0];
      H[c] = wk * vs[a][1];
    }
  }
  const int(&k_offset)[S] = st.offset[2];
  // A row's term: node k's component a takes s u[3k + a].
  struct Term {
    double s;
    const double* u;
  };
  // The arrays with the layout fixed at compile time: a blocked index costs a shift, a mask
  // and a multiply by a constant, where the plain array's costs none.
  auto rows = [&](auto contiguous, auto array_of) {
    constexpr bool kContiguous = decltype(contiguous)::value;
    const auto mass = array_of(grid.mass);
    const auto momentum = array_of(grid.momentum);
    const auto force = array_of(grid.force);
    // array[row + k_offset[k]][a] += the terms' sum over the row's S nodes (one vector
    // expression when the row is contiguous).
    auto add_row = [&](const auto& array, int row, const auto&... terms) {
      double sum[R];
      for (int c = 0; c < R; ++c) sum[c] = ((terms.s * terms.u[c]) + ...);
      if constexpr (kContiguous) {
        double* out = array[static_cast<std::size_t>(row + k_offset[0])].data();
        for (int c = 0; c < R; ++c) out[c] += sum[c];
      } else {
        for (int k = 0; k < S; ++k) {
          double* out = array[static_cast<std::size_t>(row + k_offset[k])].data();
          for (int a = 0; a < 3; ++a) out[a] += sum[3 * k + a];
        }
      }
    };
    for (int i = 0; i < S; ++i) {
      for (int j = 0; j < S; ++j) {
        const double wij = w[0][i] * w[1][j];
        const int row = st.offset[0][i] + st.offset[1][j];
        add_row(momentum, row, Term{wij, P}, Term{wij * dx[0][i], U}, Term{wij * dx[1][j], V});
        if (body_force == nullptr) continue;
        if (separate_force) {
          add_row(force, row, Term{wij, F}, Term{g[0][i] * w[1][j], G}, Term{w[0][i] * g[1][j], H});
        }
        const double wm = wij * m;
        for (int k = 0; k < S; ++k) {
          const int node = kContiguous ? row + k_offset[0] + k : row + k_offset[k];
          mass[static_cast<std::size_t>(node)] += wm * w[2][k];
        }
      }
    }
  };
  auto rows_in = [&](auto contiguous) {
    if (grid.sparse) {
      rows(contiguous, [&](const auto& a) { return grid.template access<true>(a); });
    } else {
      rows(contiguous, [&](const auto& a) { return grid.template access<false>(a); });
    }
  };
  if (st.row_contiguous) {
    rows_in(std::true_type{});
  } else {
    rows_in(std::false_type{});
  }
}

// Scatter mass and momentum (APIC adds m_p C_p (x_I - x_p), Jiang et al. 2015 eq. 12) and, with
// forces, f_I = -V_p sigma_p grad N_I + m_p N_I b_p. Slabs of one parity run in parallel: a
// particle's stencil reaches at most 2 nodes past its slab, and slab_width = 4 > 2 + 1.
// MLS-MPM scatters the momentum after the force, p_I + dt f_I, as Hu et al. (2018) do, and leaves
// the force array at zero: its force has the momentum's form N (x_I - x_p), so one row update
// serves both (a node's mass and three momentum components written instead of seven), and nothing
// reads the old grid momentum (MLS has no remap; the scenes it runs are APIC, and a test's FLIP
// keeps the force apart: force_in_momentum()).
template <int D>
template <class Shape>
void Solver<D>::scatter(bool with_force, double dt) {
  auto& P = particles;
  const bool apic = scene_.transfer == Transfer::apic;
  // MLS-MPM: the force -V sigma D^-1 (x_I - x_p) N_I in place of -V sigma grad N_I (the quadratic
  // B-spline's D^-1, the one kernel the scene accepts with it).
  const bool mls = scene_.update == UpdateScheme::mls;
  const bool fold = force_in_momentum();
  const double inv_d = BSpline2Shape::inverse_inertia(grid.inv_h);
  // f(mass, momentum, force) with the grid's layout fixed at compile time (Grid::access).
  auto in_layout = [&](auto&& f) {
    if (grid.sparse) {
      f(grid.template access<true>(grid.mass), grid.template access<true>(grid.momentum),
        grid.template access<true>(grid.force));
    } else {
      f(grid.template access<false>(grid.mass), grid.template access<false>(grid.momentum),
        grid.template access<false>(grid.force));
    }
  };
  auto scatter_one = [&](std::size_t p) {
    if (owned_by_layer(p)) return;  // the boundary grid owns it (layer_scatter)
    const Stencil<D, Shape> st(grid, P.position[p], P.half_width[p]);
    const double m = P.mass[p];
    // Plain scalars in the node loop (as in sample_grid(): Eigen 3-vector temporaries there cost
    // a store-forwarding stall per node).
    double v[D], C[D][D] = {};
    for (int a = 0; a < D; ++a) {
      v[a] = P.velocity[p][a];
      for (int b = 0; b < D; ++b) C[a][b] = apic ? P.affine[p](a, b) : 0.0;
    }
    if (with_force) {
      const Mat<D> stress = -(mls ? inv_d : 1.0) * P.volume0[p] *
                            P.deformation_gradient[p].determinant() * P.stress[p];
      double vs[D][D], mb[D];
      for (int a = 0; a < D; ++a) {
        mb[a] = m * body_acceleration_[P.body[p]][a];
        for (int b = 0; b < D; ++b) vs[a][b] = stress(a, b);
      }
      if constexpr (D == 3) {
        scatter_factorised(st, m, v, C, &mb, &vs, mls, fold, dt);
        return;
      }
      in_layout([&](const auto& mass, const auto& momenta, const auto& forces) {
        st.for_each(grid, [&](int node, double N, const Vec<D>& dN, const Vec<D>& dx) {
          const double Nm = N * m;
          const auto n = static_cast<std::size_t>(node);
          mass[n] += Nm;
          double* momentum = momenta[n].data();
          double* force = forces[n].data();
          for (int a = 0; a < D; ++a) {
            double va = v[a], fa = N * mb[a];
            for (int b = 0; b < D; ++b) {
              va += C[a][b] * dx[b];
              fa += vs[a][b] * (mls ? N * dx[b] : dN[b]);
            }
            if (fold) {
              momentum[a] += Nm * va + dt * fa;
            } else {
              momentum[a] += Nm * va;
              force[a] += fa;
            }
          }
        });
      });
    } else {
      if constexpr (D == 3) {
        scatter_factorised(st, m, v, C, nullptr, nullptr, false, false, 0.0);
        return;
      }
      in_layout([&](const auto& /*mass*/, const auto& momenta, const auto& /*forces*/) {
        st.for_each(grid, [&](int node, double N, const Vec<D>& /*dN*/, const Vec<D>& dx) {
          const double Nm = N * m;
          double* momentum = momenta[static_cast<std::size_t>(node)].data();
          for (int a = 0; a < D; ++a) {
            double va = v[a];
            for (int b = 0; b < D; ++b) va += C[a][b] * dx[b];
            momentum[a] += Nm * va;
          }
        });
      });
    }
  };
  const int slabs = static_cast<int>(slab_start_.size()) - 1;
  for (int parity = 0; parity < 2; ++parity) {
    tbb::parallel_for(0, (slabs - parity + 1) / 2, [&](int k) {
      const int slab = 2 * k + parity;
      for (int i = slab_start_[slab]; i < slab_start_[slab + 1]; ++i) scatter_one(slab_order_[i]);
    });
  }
}

template <int D>
void Solver<D>::particles_to_grid(double dt) {
  locate_in_layers();
  lap(&PhaseTimes::locate);
  bin_particles_into_slabs();
  grid.begin_marking();
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, particles.size(), 4096), [&](const auto& r) {
    for (std::size_t p = r.begin(); p != r.end(); ++p) {
      grid.mark(particles.position[p]);
    }
  });
  grid.finish_marking();
  tbb::parallel_for(std::size_t{0}, grid.previous_blocks.size(),
                    [&](std::size_t k) { grid.clear_previous(k); });
  grid.release_idle();
  dispatch_shape(scene_.shape, [&](auto shape) { scatter<decltype(shape)>(true, dt); });
  grid.masses_changed();
  layer_scatter(true);
  lap(&PhaseTimes::particles_to_grid);
}

template <int D>
template <class F>
void Solver<D>::for_each_active_node(F&& f) {
  tbb::parallel_for(std::size_t{0}, grid.active_blocks.size(),
                    [&](std::size_t b) { grid.for_each_node(grid.active_blocks[b], f); });
}

template <int D>
void Solver<D>::update_grid(double dt) {
  tbb::parallel_for(std::size_t{0}, grid.active_blocks.size(), [&](std::size_t b) {
    grid.for_each_run(grid.active_blocks[b], [&](int first, int count) {
      // A run's nodes are adjacent in every array.
      const auto n = static_cast<std::size_t>(first);
      const double* m = &grid.mass[n];
      const Vec<D>* p = &grid.momentum[n];
      const Vec<D>* f = &grid.force[n];
      Vec<D>* v = &grid.velocity[n];
      Vec<D>* v_new = &grid.velocity_new[n];
      for (int k = 0; k < count; ++k) {
        node_velocities<D>(m[k], p[k], f[k], dt, mass_threshold_, v[k], v_new[k]);
      }
    });
  });
  layer_update(dt);
}

template <int D>
void Solver<D>::constrain_walls(NodeField<Vec<D>>& velocity, bool record) {
  for (std::size_t w = 0; w < scene_.walls.size(); ++w) {
    const BoxWall& wall = scene_.walls[w];
    Vec<D> normal = Vec<D>::Zero();
    normal[wall.axis] = wall.side < 0 ? 1.0 : -1.0;
    Vec<D> impulse = Vec<D>::Zero();
    std::visit(
        [&](const auto& condition) {
          for_each_in_active_blocks(wall_node_runs_[w], [&](std::size_t k) {
            const int n = wall_nodes_[w][k];
            const double m = grid.mass[n];
            if (m <= mass_threshold_) return;
            const Vec<D> before = velocity[n];
            velocity[n] = constrain_velocity<D>(condition, wall.contact.separable, normal, before);
            impulse += m * (velocity[n] - before);
          });
          // A bonded wall is a symmetry plane of the velocity field: ghost nodes take the
          // mirror image of the node inside (normal component odd; tangential odd for sticky,
          // even otherwise), so wide kernels (B-spline, GIMP) see the wall where it is rather
          // than a wall smeared over the ghost layer.
          for_each_in_active_blocks(wall_ghost_runs_[w], [&](std::size_t k) {
            const auto& [ghost, mirror] = wall_ghosts_[w][k];
            const double m = grid.mass[ghost];
            if (m <= mass_threshold_) return;
            const Vec<D> before = velocity[ghost];
            const Vec<D>& inside = velocity[mirror];
            if constexpr (std::is_same_v<std::decay_t<decltype(condition)>, Sticky>) {
              velocity[ghost] = -inside;
            } else {
              velocity[ghost] = inside - 2.0 * inside.dot(normal) * normal;
            }
            impulse += m * (velocity[ghost] - before);
          });
        },
        wall.contact.condition);
    if (record) wall_impulse_[w] += pad3<D>(impulse);
  }
  constrain_sdf_walls(velocity, record);
}

template <int D>
void Solver<D>::apply_walls() {
  constrain_walls(grid.velocity_new, true);
  layer_walls(&DualWall<D>::velocity_new, true);
}

template <int D>
void Solver<D>::reset_wall_impulses() {
  std::fill(wall_impulse_.begin(), wall_impulse_.end(), Eigen::Vector3d::Zero());
}

// Interpolation of a grid velocity field at one particle. Nodes below the mass threshold carry
// no velocity, so they are treated as moving with the particle: sums run over active nodes only,
// the value is renormalised by the active weight, and gradients use sum_I (v_I - v_p) grad N_I
// (valid because sum_I grad N_I = 0). Without this a particle whose stencil touches an empty
// node (a free surface, a particle on a grid line) sees a spurious gradient -v/h.
template <int D>
struct GridSample {
  Vec<D> value = Vec<D>::Zero();      ///< sum N v / sum N
  Vec<D> increment = Vec<D>::Zero();  ///< sum N (v_new - v), for FLIP
  Mat<D> gradient = Mat<D>::Zero();   ///< sum (v - value) grad N^T
  Mat<D> moment = Mat<D>::Zero();     ///< sum N (v - value) (x_I - x_p)^T, for APIC B_p
};

/// What sample_grid() accumulates besides the value (compile-time, so each pass pays only for
/// what its scheme uses).
enum SampleParts : unsigned { kIncrement = 1U, kGradient = 2U, kMoment = 4U };

// The sums run in plain scalars and are copied out at the end. With Eigen 3-vectors (the
// accumulators, N v_I) the compiler built each product on the stack in 8-byte pieces and read it
// back as one 16-byte vector, a store-forwarding stall at every node that took 64% of the
// standard step (perf, session of 2026-12-01).
//
// In 3D a stencil whose nodes all carry mass (a particle inside the material) takes the sums
// axis by axis instead (sum factorisation: the kernel is a tensor product, so e.g.
// sum_ijk w_i w_j dw_k v_ijk = sum_i w_i sum_j w_j sum_k dw_k v_ijk): about half the
// arithmetic of the node loop, the same sums in another order. The generic loop serves
// stencils that touch an empty node, where the sums skip it.
//
// Dense: the grid's dense layout, where node (i, j, k) of the stencil is its first node plus
// i stride_0 + j stride_1 + k (constant offsets along a row); otherwise the stencil's per-axis
// offsets locate each node (a row of the sparse layout may cross a block).
template <unsigned Parts, bool Dense, class Shape>
bool sample_grid_factorised(Grid<3>& grid, const Stencil<3, Shape>& st, const NodeField<Vec<3>>& v,
                            const NodeField<Vec<3>>& v_old, double threshold, GridSample<3>& s) {
  constexpr int S = Shape::support;
  constexpr bool kG = (Parts & kGradient) != 0, kM = (Parts & kMoment) != 0;
  constexpr bool kI = (Parts & kIncrement) != 0;
  const int first = st.offset[0][0] + st.offset[1][0] + st.offset[2][0];  // the stencil's
  const int s0 = grid.local_stride[0], s1 = grid.local_stride[1];         // dense: the strides
  auto row_of = [&](int i, int j) { return first + i * s0 + j * s1; };    // dense
  // Node (i, j, k) of an array of Size-byte values is at base + row(i, j) + along(k) bytes:
  // dense, the row's first node and k values on; sparse, the per-axis byte offsets summed
  // (Grid::byte_offset(), so the blocked layout costs no more than a table lookup per axis).
  constexpr std::ptrdiff_t kScalar = sizeof(double), kVector = sizeof(Vec<3>);
  std::ptrdiff_t o_scalar[3][S], o_vector[3][S];
  if constexpr (!Dense) {
    for (int d = 0; d < 3; ++d) {
      for (int k = 0; k < S; ++k) {
        o_scalar[d][k] = grid.template byte_offset<kScalar>(st.offset[d][k]);
        o_vector[d][k] = grid.template byte_offset<kVector>(st.offset[d][k]);
      }
    }
  }
  auto row_bytes = [&](int i, int j, std::ptrdiff_t size, const std::ptrdiff_t(&o)[3][S]) {
    if constexpr (Dense) return row_of(i, j) * size;
    return o[0][i] + o[1][j];
  };
  auto along = [&](int k, std::ptrdiff_t size, const std::ptrdiff_t(&o)[3][S]) {
    if constexpr (Dense) return k * size;
    return o[2][k];
  };
  const char* mass = grid.mass.base();
  const char* vnew = v.base();
  const char* vold = v_old.base();
  // Does every node carry mass? As found for the stencil's first node since the masses changed
  // (Grid::stencil_mark, whose 3^3 nodes are the stencil of a 3-node kernel: quadratic
  // B-spline, GIMP), or checked here: 1 load in place of 27 for 7 particles in 8.
  const bool marked = S == 3 && grid.stencil_epoch > 0;  // Grid::masses_changed() has run
  std::int8_t* marks = grid.stencil_mark.data();
  const auto epoch = static_cast<std::int8_t>(grid.stencil_epoch);
  const std::int8_t known =
      marked ? std::atomic_ref<std::int8_t>(marks[first]).load(std::memory_order_relaxed) : 0;
  bool full = marked && known == epoch;
  if (!full && !(marked && known == -epoch)) {
    full = true;
    for (int i = 0; i < S; ++i) {
      for (int j = 0; j < S; ++j) {
        const char* row = mass + row_bytes(i, j, kScalar, o_scalar);
        for (int k = 0; k < S; ++k) {
          full &= *reinterpret_cast<const double*>(row + along(k, kScalar, o_scalar)) > threshold;
        }
      }
    }
    if (marked) {
      std::atomic_ref<std::int8_t>(marks[first])
          .store(full ? epoch : static_cast<std::int8_t>(-epoch), std::memory_order_relaxed);
    }
  }
  if (!full) return false;
  const auto& w = st.w;
  const auto& dw = st.dw;
  double wx[3][S];  // w * (x_I - x_p) per axis
  double sum_w[3] = {}, sum_dw[3] = {}, sum_wx[3] = {};
  for (int d = 0; d < 3; ++d) {
    for (int k = 0; k < S; ++k) {
      wx[d][k] = w[d][k] * st.dx[d][k];
      sum_w[d] += w[d][k];
      sum_dw[d] += dw[d][k];
      sum_wx[d] += wx[d][k];
    }
  }
  // Level i sums: value, increment, gradient columns, moment columns.
  double value[3] = {}, increment[3] = {}, gradient[3][3] = {}, moment[3][3] = {};
  for (int i = 0; i < S; ++i) {
    double jv[3] = {}, jinc[3] = {}, jdy[3] = {}, jdz[3] = {}, jmy[3] = {}, jmz[3] = {};
    for (int j = 0; j < S; ++j) {
      const std::ptrdiff_t row = row_bytes(i, j, kVector, o_vector);
      double kv[3] = {}, kinc[3] = {}, kd[3] = {}, km[3] = {};
      for (int k = 0; k < S; ++k) {
        const std::ptrdiff_t node = row + along(k, kVector, o_vector);
        const auto* vn = reinterpret_cast<const double*>(vnew + node);
        for (int a = 0; a < 3; ++a) {
          kv[a] += w[2][k] * vn[a];
          if constexpr (kG) kd[a] += dw[2][k] * vn[a];
          if constexpr (kM) km[a] += wx[2][k] * vn[a];
        }
        if constexpr (kI) {
          const auto* vo = reinterpret_cast<const double*>(vold + node);
          for (int a = 0; a < 3; ++a) kinc[a] += w[2][k] * (vn[a] - vo[a]);
        }
      }
      for (int a = 0; a < 3; ++a) {
        jv[a] += w[1][j] * kv[a];
        if constexpr (kI) jinc[a] += w[1][j] * kinc[a];
        if constexpr (kG) {
          jdy[a] += dw[1][j] * kv[a];
          jdz[a] += w[1][j] * kd[a];
        }
        if constexpr (kM) {
          jmy[a] += wx[1][j] * kv[a];
          jmz[a] += w[1][j] * km[a];
        }
      }
    }
    for (int a = 0; a < 3; ++a) {
      value[a] += w[0][i] * jv[a];
      if constexpr (kI) increment[a] += w[0][i] * jinc[a];
      if constexpr (kG) {
        gradient[a][0] += dw[0][i] * jv[a];
        gradient[a][1] += w[0][i] * jdy[a];
        gradient[a][2] += w[0][i] * jdz[a];
      }
      if constexpr (kM) {
        moment[a][0] += wx[0][i] * jv[a];
        moment[a][1] += w[0][i] * jmy[a];
        moment[a][2] += w[0][i] * jmz[a];
      }
    }
  }
  // The generic loop's normalisation and corrections, with its sums of N, grad N and
  // N (x_I - x_p) over the stencil, factorised too.
  const double weight = sum_w[0] * sum_w[1] * sum_w[2];
  const double grad_sum[3] = {sum_dw[0] * sum_w[1] * sum_w[2], sum_w[0] * sum_dw[1] * sum_w[2],
                              sum_w[0] * sum_w[1] * sum_dw[2]};
  const double dx_sum[3] = {sum_wx[0] * sum_w[1] * sum_w[2], sum_w[0] * sum_wx[1] * sum_w[2],
                            sum_w[0] * sum_w[1] * sum_wx[2]};
  for (int a = 0; a < 3; ++a) s.value[a] = value[a] / weight;
  for (int a = 0; a < 3; ++a) {
    if constexpr (kI) s.increment[a] = increment[a];
    for (int b = 0; b < 3; ++b) {
      if constexpr (kG) s.gradient(a, b) = gradient[a][b] - s.value[a] * grad_sum[b];
      if constexpr (kM) s.moment(a, b) = moment[a][b] - s.value[a] * dx_sum[b];
    }
  }
  return true;
}

// The node loop of sample_grid() with the grid's layout fixed at compile time.
template <unsigned Parts, bool Sparse, int D, class Shape>
GridSample<D> sample_grid_nodes(const Grid<D>& grid, const Stencil<D, Shape>& st,
                                const NodeField<Vec<D>>& v, const NodeField<Vec<D>>& v_old,
                                double threshold) {
  const auto mass = grid.template access<Sparse>(grid.mass);
  const auto vnew = grid.template access<Sparse>(v);
  const auto vold = grid.template access<Sparse>(v_old);
  double weight = 0.0;
  double value[D] = {}, increment[D] = {}, grad_sum[D] = {}, dx_sum[D] = {};
  double gradient[D][D] = {}, moment[D][D] = {};
  st.for_each(grid, [&](int node, double N, const Vec<D>& dN, const Vec<D>& dx) {
    const auto n = static_cast<std::size_t>(node);
    if (mass[n] <= threshold) return;
    const double* vn = vnew[n].data();
    weight += N;
    for (int a = 0; a < D; ++a) value[a] += N * vn[a];
    if constexpr ((Parts & kIncrement) != 0) {
      const double* vo = vold[n].data();
      for (int a = 0; a < D; ++a) increment[a] += N * (vn[a] - vo[a]);
    }
    if constexpr ((Parts & kGradient) != 0) {
      for (int a = 0; a < D; ++a) {
        grad_sum[a] += dN[a];
        for (int b = 0; b < D; ++b) gradient[a][b] += vn[a] * dN[b];
      }
    }
    if constexpr ((Parts & kMoment) != 0) {
      for (int a = 0; a < D; ++a) {
        dx_sum[a] += N * dx[a];
        const double nv = N * vn[a];
        for (int b = 0; b < D; ++b) moment[a][b] += nv * dx[b];
      }
    }
  });
  GridSample<D> s;
  if (weight <= 0.0) return s;
  for (int a = 0; a < D; ++a) s.value[a] = value[a] / weight;
  for (int a = 0; a < D; ++a) {
    if constexpr ((Parts & kIncrement) != 0) s.increment[a] = increment[a];
    for (int b = 0; b < D; ++b) {
      if constexpr ((Parts & kGradient) != 0) {
        s.gradient(a, b) = gradient[a][b] - s.value[a] * grad_sum[b];
      }
      if constexpr ((Parts & kMoment) != 0) s.moment(a, b) = moment[a][b] - s.value[a] * dx_sum[b];
    }
  }
  return s;
}

// `grid` is the solver's, whose stencil marks the factorised path reads and writes (in 3D):
// valid while its masses are those of the last Grid::masses_changed().
template <unsigned Parts, int D, class Shape>
GridSample<D> sample_grid(Grid<D>& grid, const Stencil<D, Shape>& st, const NodeField<Vec<D>>& v,
                          const NodeField<Vec<D>>& v_old, double threshold) {
  if constexpr (D == 3) {
    GridSample<3> s;
    if (grid.sparse ? sample_grid_factorised<Parts, false>(grid, st, v, v_old, threshold, s)
                    : sample_grid_factorised<Parts, true>(grid, st, v, v_old, threshold, s)) {
      return s;
    }
  }
  return grid.sparse ? sample_grid_nodes<Parts, true>(grid, st, v, v_old, threshold)
                     : sample_grid_nodes<Parts, false>(grid, st, v, v_old, threshold);
}

// Gather the new velocity (and for FLIP the displacement) at x_p^n. APIC keeps C_p = B_p D_p^{-1}
// with D_p = h^2/4 I for the quadratic B-spline (Jiang et al. 2015 eq. 10); for the linear
// kernel B_p D_p^{-1} = sum_I v_I grad N_I^T (ibid., section 5.3), which is also used for GIMP:
// both are exact for affine fields. USL also takes the velocity gradient here, and updates the
// stress of the particles the standard grid alone moves with it.
template <int D>
template <class Shape>
void Solver<D>::gather(double dt, Reach reach) {
  auto& P = particles;
  const bool apic = scene_.transfer == Transfer::apic;
  const bool usl = scene_.update != UpdateScheme::musl;  // USL or MLS: the gradient now
  const bool mls = scene_.update == UpdateScheme::mls;
  const bool displace = !P.displacement.empty();
  constexpr bool bspline = std::is_same_v<Shape, BSpline2Shape>;
  const double alpha = scene_.flip_blend;
  const double inv_d = BSpline2Shape::inverse_inertia(grid.inv_h);
  auto pass = [&](auto parts) {
    constexpr unsigned Parts = decltype(parts)::value;
    // Gathers particle p; with the gradient (USL), true if its stress is to be updated now.
    auto sample = [&](std::size_t p, Mat<D>& L) {
      if (!takes(reach, p) || owned_by_layer(p)) return false;  // layer_gather
      const Stencil<D, Shape> st(grid, P.position[p], P.half_width[p]);
      const GridSample<D> s =
          sample_grid<Parts>(grid, st, grid.velocity_new, grid.velocity, mass_threshold_);
      if constexpr ((Parts & kIncrement) != 0) {
        P.velocity[p] = alpha * (P.velocity[p] + s.increment) + (1.0 - alpha) * s.value;
      } else {
        P.velocity[p] = s.value;
        if constexpr (bspline) {
          P.affine[p] = s.moment * inv_d;
        } else {
          P.affine[p] = s.gradient;
        }
      }
      if (displace) P.displacement[p] = dt * s.value;
      if constexpr ((Parts & kGradient) != 0) {
        if (!usl) return false;  // the gradient was the affine matrix (linear kernel, GIMP)
        return take_gradient(p, s.gradient, L);  // Enhanced layer particles: layer_gather adds
      } else if constexpr (bspline && (Parts & kMoment) != 0) {
        // MLS-MPM: the velocity gradient is the affine matrix B_p D^-1.
        if (mls) return take_gradient(p, P.affine[p], L);
      }
      return false;
    };
    if (usl) {
      sample_and_update_stress(dt, sample);
      return;
    }
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, P.size(), 1024), [&](const auto& r) {
      Mat<D> unused;
      for (std::size_t p = r.begin(); p != r.end(); ++p) sample(p, unused);
    });
  };
  using std::integral_constant;
  if (apic) {
    constexpr unsigned affine = bspline ? kMoment : kGradient;
    if (mls && bspline) {
      pass(integral_constant<unsigned, kMoment>{});
    } else if (usl) {
      pass(integral_constant<unsigned, affine | kGradient>{});
    } else {
      pass(integral_constant<unsigned, affine>{});
    }
  } else if (usl) {
    pass(integral_constant<unsigned, kIncrement | kGradient>{});
  } else {
    pass(integral_constant<unsigned, kIncrement>{});
  }
}

// MUSL: the velocity gradient from the remapped field, and the stress update of the particles
// the standard grid alone moves.
template <int D>
template <class Shape>
void Solver<D>::gather_velocity_gradient(double dt, Reach reach) {
  auto& P = particles;
  sample_and_update_stress(dt, [&](std::size_t p, Mat<D>& L) {
    if (!takes(reach, p) || owned_by_layer(p)) return false;  // layer_gather_gradient
    const Stencil<D, Shape> st(grid, P.position[p], P.half_width[p]);
    // Enhanced layer particles: layer_gather_gradient adds the layer's.
    return take_gradient(
        p, sample_grid<kGradient>(grid, st, grid.velocity, grid.velocity, mass_threshold_).gradient,
        L);
  });
}

// Runs sample(p, L) over the particles, material group by group, in chunks: it gathers particle
// p and, when it returns true, leaves in L the velocity gradient its constitutive update takes
// at once (a chunk's gradients wait in a buffer on the stack, so no per-particle array holds
// them: 72 bytes a particle in 3D). The pass's time is split between the phases
// grid_to_particles and stress in proportion to the time each part took.
template <int D>
template <class Sample>
void Solver<D>::sample_and_update_stress(double dt, Sample&& sample) {
  auto& P = particles;
  using Clock = std::chrono::steady_clock;
  constexpr std::size_t kChunk = 128;
  lap(&PhaseTimes::grid_to_particles);
  tbb::combinable<std::array<double, 2>> seconds([] { return std::array<double, 2>{}; });
  for (const auto& [begin, end] : groups_) {
    std::visit(
        [&, b = begin, e = end](const auto& material) {
          tbb::parallel_for(tbb::blocked_range<std::size_t>(b, e, kChunk), [&](const auto& r) {
            std::array<Mat<D>, kChunk> L;
            std::array<bool, kChunk> now{};
            std::array<double, 2>& local = seconds.local();
            for (std::size_t first = r.begin(); first < r.end(); first += kChunk) {
              const std::size_t n = std::min(kChunk, r.end() - first);
              const auto t0 = Clock::now();
              for (std::size_t k = 0; k < n; ++k) now[k] = sample(first + k, L[k]);
              const auto t1 = Clock::now();
              for (std::size_t k = 0; k < n; ++k) {
                if (!now[k]) continue;
                const std::size_t p = first + k;
                mpm::update_stress<D>(material, L[k], dt, P.deformation_gradient[p], P.stress[p],
                                      P.state[p]);
              }
              const auto t2 = Clock::now();
              local[0] += std::chrono::duration<double>(t1 - t0).count();
              local[1] += std::chrono::duration<double>(t2 - t1).count();
            }
          });
        },
        scene_.materials[static_cast<std::size_t>(P.material[begin])].model);
  }
  const std::array<double, 2> total =
      seconds.combine([](std::array<double, 2> a, const std::array<double, 2>& b) {
        return std::array<double, 2>{a[0] + b[0], a[1] + b[1]};
      });
  const Clock::time_point now = Clock::now();
  const double wall = std::chrono::duration<double>(now - lap_start_).count();
  const double share = total[0] + total[1] > 0.0 ? total[1] / (total[0] + total[1]) : 0.0;
  times_.stress += share * wall;
  times_.grid_to_particles += (1.0 - share) * wall;
  lap_start_ = now;
}

// A coupling changes few standard-grid nodes (Blending: rows of its R^A; Enhanced: rows of its
// R^A on Gamma and its layer particles' stencil nodes) besides its boundary grid, so the
// particles whose stencils reach none of them and that no layer holds gather the same values
// before it as after (bit for bit): one core can gather them while the other couples (its
// solves are mostly serial and would leave a core idle), and the rest after. Whether that pays
// depends on the coupling and on the machine: a coupling with parallel parts of its own
// (Enhanced's assembly) runs longer beside the gather than alone on both cores, and on the
// shared two-core host of docs/performance.md the mortar floor's (refined against an aged
// factor, 2.4 ms) gains by the overlap under MLS-MPM and not under MUSL, Enhanced's neither. So
// each call measures its time from the coupling's start to the gather's end and runs the way
// that has lately been faster (couple_beside_next()). The phase timers charge an overlapped
// coupling its own duration, taken from what the pass was charged over the same time, so the
// phases still add up to the step.
template <int D>
template <class Pass>
void Solver<D>::couple_beside(bool remapped, Pass&& pass) {
  // Nothing to overlap, nor to time, where no wall has layer particles this step (its coupling
  // is no work).
  const bool coupled =
      std::ranges::any_of(dual_, [](const auto& w) { return w.layer_particles > 0; });
  using Clock = std::chrono::steady_clock;
  const int call = remapped ? 1 : 0;
  const bool beside = coupled && couple_beside_next(call);
  const auto start = Clock::now();
  if (!beside) {
    layer_couple(remapped);
    lap(&PhaseTimes::coupling);
    pass(Reach::all);
  } else {
    const double gather_before = times_.grid_to_particles, stress_before = times_.stress;
    // The coupling is the task (the other thread takes it) and this thread gathers the free
    // particles, which the other joins when it has coupled. (The other way round, the free pass
    // the task and the coupling this thread's, both gathers ran half as slow again per particle
    // on the two-core host: the mortar floor under MLS-MPM 1.50-1.71 times the standard step
    // against 1.39, docs/performance.md.) The coupling touches no phase timer: its own duration
    // is taken inside the task.
    double coupling = 0.0;
    tbb::task_group coupler;
    coupler.run([&] {
      const auto begin = Clock::now();
      layer_couple(remapped);
      coupling = std::chrono::duration<double>(Clock::now() - begin).count();
    });
    pass(Reach::free);
    coupler.wait();
    lap(&PhaseTimes::grid_to_particles);
    const double gathered = times_.grid_to_particles - gather_before;
    const double stressed = times_.stress - stress_before;
    const double charged = gathered + stressed;
    if (charged > 0.0) {
      const double moved = std::min(coupling, charged);
      times_.grid_to_particles -= moved * gathered / charged;
      times_.stress -= moved * stressed / charged;
      times_.coupling += moved;
    }
    pass(Reach::near);
  }
  if (!coupled) return;
  OverlapTimes& t = overlap_[static_cast<std::size_t>(call)];
  const auto way = static_cast<std::size_t>(beside ? 1 : 0);
  const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
  // The mean of about the last four runs: the host's speed drifts, and the coupling's length
  // with the flow.
  t.mean[way] = t.runs[way] == 0 ? seconds : t.mean[way] + 0.25 * (seconds - t.mean[way]);
  ++t.runs[way];
}

// Whether call `call` of couple_beside() (0: the gather's, 1: the MUSL remap's) overlaps this
// time: each way twice first, alternately, then the one with the smaller recent mean, and the
// other every 16th call (a way that lost once is measured again as things change).
template <int D>
bool Solver<D>::couple_beside_next(int call) const {
  if (overlap_mode_ != CouplingOverlap::adaptive) return overlap_mode_ == CouplingOverlap::beside;
  const OverlapTimes& t = overlap_[static_cast<std::size_t>(call)];
  if (t.runs[0] < 2 || t.runs[1] < 2) return t.runs[1] <= t.runs[0];
  const bool faster = t.mean[1] <= t.mean[0];
  return (t.runs[0] + t.runs[1] + 1) % 16 == 0 ? !faster : faster;  // this call's number
}

template <int D>
void Solver<D>::grid_to_particles(double dt) {
  const bool usl = scene_.update != UpdateScheme::musl;  // USL or MLS
  dispatch_shape(scene_.shape, [&](auto shape) {
    using Shape = decltype(shape);
    couple_beside(false, [&](Reach reach) { gather<Shape>(dt, reach); });
    layer_gather(dt);
    if (!usl) {
      // MUSL (Sulsky et al. 1995): map the updated particle momenta back to the grid at x_p^n
      // and take the strain rate from that smoother field (both grids, coupled again on Phi).
      // (The free particles' part of this remap beside the coupling too was slower: the scatter
      // in two halves, docs/performance.md.)
      for_each_active_node([&](std::size_t n) { grid.momentum[n].setZero(); });
      scatter<Shape>(false, 0.0);
      for_each_active_node([&](std::size_t n) {
        const double m = grid.mass[n];
        grid.velocity[n] = m > mass_threshold_ ? Vec<D>(grid.momentum[n] / m) : Vec<D>::Zero();
      });
      lap(&PhaseTimes::grid_to_particles);
      constrain_walls(grid.velocity, false);
      lap(&PhaseTimes::walls);
      layer_remap();
      lap(&PhaseTimes::grid_to_particles);
      couple_beside(true, [&](Reach reach) { gather_velocity_gradient<Shape>(dt, reach); });
      layer_gather_gradient();
    }
  });
  lap(&PhaseTimes::grid_to_particles);
  update_layer_stress(dt);
  lap(&PhaseTimes::stress);
  advect_and_check(dt);
  lap(&PhaseTimes::advect);
}

// The constitutive update of the layer particles, whose velocity gradient the boundary grid
// gave (or completed: Enhanced).
template <int D>
void Solver<D>::update_layer_stress(double dt) {
  auto& P = particles;
  tbb::parallel_for(
      tbb::blocked_range<std::size_t>(0, layer_list_.size(), 256), [&](const auto& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i) {
          const auto p = static_cast<std::size_t>(layer_list_[i]);
          std::visit(
              [&](const auto& material) {
                mpm::update_stress<D>(material, layer_gradient_[i], dt, P.deformation_gradient[p],
                                      P.stress[p], P.state[p]);
              },
              scene_.materials[static_cast<std::size_t>(P.material[p])].model);
        }
      });
}

// Move the particles, track the fastest one for the CFL step, and find the first particle that
// went bad (non-finite, inverted, outside the grid) so the run can stop with its name.
template <int D>
void Solver<D>::advect_and_check(double dt) {
  auto& P = particles;
  const double lo_g = 1.0;
  const Vec<D> hi_g = (grid.nodes.template cast<double>().array() - 2.0).matrix();
  struct Scan {
    double max_speed = 0.0;
    std::size_t first_bad = static_cast<std::size_t>(-1);
  };
  // By locate_in_layers()'s chunks, each adding its farthest move to its travel.
  constexpr std::size_t kChunk = kLocateChunk;
  const std::size_t chunks = (P.size() + kChunk - 1) / kChunk;
  const bool travels = chunk_travel_.size() == chunks;
  const Scan scan = tbb::parallel_reduce(
      tbb::blocked_range<std::size_t>(0, chunks, 2), Scan{},
      [&](const auto& r, Scan s) {
        for (std::size_t chunk = r.begin(); chunk != r.end(); ++chunk) {
          double farthest = 0.0;  // squared
          const std::size_t end = std::min(P.size(), (chunk + 1) * kChunk);
          for (std::size_t p = chunk * kChunk; p != end; ++p) {
            const Vec<D> move =
                P.displacement.empty() ? Vec<D>(dt * P.velocity[p]) : P.displacement[p];
            P.position[p] += move;
            farthest = std::max(farthest, move.squaredNorm());
            const double speed = P.velocity[p].norm();
            const Vec<D> xg = (P.position[p] - grid.origin) * grid.inv_h;
            const bool ok = std::isfinite(speed) && std::isfinite(P.stress[p].sum()) &&
                            P.deformation_gradient[p].determinant() > 0.0 &&
                            (xg.array() >= lo_g).all() && (xg.array() <= hi_g.array()).all();
            if (!ok) {
              s.first_bad = std::min(s.first_bad, p);
              farthest = std::numeric_limits<double>::infinity();  // (a position not finite)
            }
            s.max_speed = std::max(s.max_speed, speed);
          }
          if (travels) chunk_travel_[chunk] += std::sqrt(farthest);
        }
        return s;
      },
      [](Scan a, const Scan& b) {
        a.max_speed = std::max(a.max_speed, b.max_speed);
        a.first_bad = std::min(a.first_bad, b.first_bad);
        return a;
      });
  max_speed_ = scan.max_speed;
  if (scan.first_bad == static_cast<std::size_t>(-1)) return;

  const std::size_t p = scan.first_bad;
  std::ostringstream what;
  what << "particle " << p << " (material \"" << scene_.materials[P.material[p]].name
       << "\", body \"" << scene_.bodies[P.body[p]].name << "\"): ";
  const double J = P.deformation_gradient[p].determinant();
  if (!std::isfinite(P.velocity[p].norm())) {
    what << "velocity is not finite " << format_vec<D>(P.velocity[p]);
  } else if (!std::isfinite(P.stress[p].sum())) {
    what << "stress is not finite";
  } else if (!(J > 0.0)) {
    what << "deformation gradient inverted (det F = " << J << ")";
  } else {
    what << "left the grid at x = " << format_vec<D>(P.position[p]) << " (grid box "
         << format_vec<D>(to_vec<D>(scene_.box_min)) << " to "
         << format_vec<D>(to_vec<D>(scene_.box_max)) << ")";
  }
  fault_ = what.str();
}

template <int D>
Energies Solver<D>::energies() const {
  const auto& P = particles;
  Energies e;
  for (std::size_t p = 0; p < P.size(); ++p) {
    e.kinetic += 0.5 * P.mass[p] * P.velocity[p].squaredNorm();
    e.gravity -= P.mass[p] * gravity_.dot(P.position[p]);
  }
  for (const auto& [begin, end] : groups_) {
    std::visit(
        [&, b = begin, en = end](const auto& material) {
          for (std::size_t p = b; p < en; ++p) {
            e.strain += strain_energy<D>(material, P.deformation_gradient[p], P.stress[p],
                                         P.volume0[p], P.state[p].stress_zz);
          }
        },
        scene_.materials[P.material[begin]].model);
  }
  return e;
}

template <int D>
Eigen::Vector3d Solver<D>::momentum() const {
  Vec<D> total = Vec<D>::Zero();
  for (std::size_t p = 0; p < particles.size(); ++p) {
    total += particles.mass[p] * particles.velocity[p];
  }
  return pad3<D>(total);
}

template <int D>
ParticleFrame Solver<D>::frame(double time, std::int64_t step) const {
  const auto& P = particles;
  ParticleFrame f;
  f.time = time;
  f.step = step;
  f.count = P.size();
  f.position.resize(3 * f.count);
  f.velocity.resize(3 * f.count);
  f.stress.assign(9 * f.count, 0.0);
  f.mass = P.mass;
  f.volume.resize(f.count);
  f.material = P.material;
  f.body = P.body;
  for (std::size_t p = 0; p < f.count; ++p) {
    const Eigen::Vector3d x = pad3<D>(P.position[p]);
    const Eigen::Vector3d v = pad3<D>(P.velocity[p]);
    for (int d = 0; d < 3; ++d) {
      f.position[3 * p + d] = x[d];
      f.velocity[3 * p + d] = v[d];
    }
    for (int i = 0; i < D; ++i) {
      for (int j = 0; j < D; ++j) f.stress[9 * p + 3 * i + j] = P.stress[p](i, j);
    }
    f.volume[p] = P.volume0[p] * P.deformation_gradient[p].determinant();
  }
  return f;
}

namespace {

// Appends the coefficients of fixed-size Eigen objects to a flat array, and reads them back.
template <class T>
std::vector<double> flatten(const std::vector<T>& values) {
  std::vector<double> flat;
  flat.reserve(values.size() * static_cast<std::size_t>(T::SizeAtCompileTime));
  for (const T& v : values) flat.insert(flat.end(), v.data(), v.data() + v.size());
  return flat;
}

template <class T>
void unflatten(const std::vector<double>& flat, std::vector<T>& values) {
  const auto size = static_cast<std::size_t>(T::SizeAtCompileTime);
  values.resize(flat.size() / size);
  for (std::size_t i = 0; i < values.size(); ++i) {
    std::copy_n(flat.begin() + static_cast<std::ptrdiff_t>(i * size), size, values[i].data());
  }
}

/// A sparse matrix as three flat arrays (compressed columns) and its shape, under key.*.
void save_sparse(Checkpoint& c, const std::string& key, Eigen::SparseMatrix<double> m) {
  m.makeCompressed();
  c.integers[key + ".shape"] = {m.rows(), m.cols()};
  c.integers[key + ".outer"].assign(m.outerIndexPtr(), m.outerIndexPtr() + m.outerSize() + 1);
  c.integers[key + ".inner"].assign(m.innerIndexPtr(), m.innerIndexPtr() + m.nonZeros());
  c.reals[key + ".values"].assign(m.valuePtr(), m.valuePtr() + m.nonZeros());
}

/// The inverse of save_sparse(); throws std::runtime_error naming the key if the arrays do not
/// make a matrix.
Eigen::SparseMatrix<double> restore_sparse(const Checkpoint& c, const std::string& key) {
  const auto& shape = c.integer(key + ".shape", 2);
  const auto& outer = c.integer(key + ".outer", static_cast<std::size_t>(shape[1]) + 1);
  const auto nonzeros = static_cast<std::size_t>(outer.back());
  const auto& inner = c.integer(key + ".inner", nonzeros);
  const auto& values = c.real(key + ".values", nonzeros);
  std::vector<Eigen::Triplet<double>> t;
  t.reserve(nonzeros);
  for (std::int64_t col = 0; col < shape[1]; ++col) {
    for (auto k = outer[col]; k < outer[col + 1]; ++k) {
      if (k < 0 || static_cast<std::size_t>(k) >= nonzeros || inner[k] < 0 ||
          inner[k] >= shape[0]) {
        throw std::runtime_error(key + ": not a sparse matrix");
      }
      t.emplace_back(static_cast<int>(inner[k]), static_cast<int>(col), values[k]);
    }
  }
  Eigen::SparseMatrix<double> m(shape[0], shape[1]);
  m.setFromTriplets(t.begin(), t.end());
  return m;
}

/// The matrix a factorisation is of (save_sparse()) and its fill-reducing ordering under
/// key.ordering: the fill L had when the ordering was made, then Eigen's P^-1 (a kept ordering,
/// SparseLdlt::analyzePattern(), is not the one a fresh analysis of the matrix would make).
void save_factorised(Checkpoint& c, const std::string& key, const Eigen::SparseMatrix<double>& m,
                     const SparseLdlt& solver) {
  save_sparse(c, key, m);
  const auto& inverse = solver.permutationPinv().indices();
  auto& saved = c.integers[key + ".ordering"];
  saved.assign(1, static_cast<std::int64_t>(solver.ordered_fill()));
  saved.insert(saved.end(), inverse.data(), inverse.data() + inverse.size());
}

/// The factorisation save_factorised() saved under key, made again into `solver` in the same
/// ordering (a checkpoint without one: Eigen's AMD, as runs made then); returns its matrix.
/// Throws std::runtime_error naming the key if the arrays do not make one, or the matrix does
/// not factorise.
Eigen::SparseMatrix<double> restore_factorised(const Checkpoint& c, const std::string& key,
                                               SparseLdlt& solver) {
  Eigen::SparseMatrix<double> m = restore_sparse(c, key);
  if (const auto it = c.integers.find(key + ".ordering"); it != c.integers.end()) {
    const std::vector<std::int64_t>& saved = it->second;
    if (saved.size() != static_cast<std::size_t>(m.rows()) + 1 || saved[0] < 0 ||
        m.rows() != m.cols()) {
      throw std::runtime_error(key + ".ordering: expected the fill and " +
                               std::to_string(m.rows()) + " unknowns");
    }
    std::vector<int> inverse(saved.size() - 1);
    for (std::size_t k = 0; k < inverse.size(); ++k) {
      const std::int64_t v = saved[k + 1];
      inverse[k] = v < 0 || v > std::numeric_limits<int>::max() ? -1 : static_cast<int>(v);
    }
    try {
      solver.analyzePattern(m, inverse, static_cast<std::size_t>(saved[0]));
    } catch (const std::invalid_argument&) {
      throw std::runtime_error(key + ".ordering: not a permutation of the unknowns");
    }
  } else {
    solver.analyzePattern(m);
  }
  solver.factorize(m);
  if (solver.info() != Eigen::Success) {
    throw std::runtime_error(key + ": the saved matrix does not factorise");
  }
  return m;
}

/// A factorisation's SparseLdlt::DroppedUse as a checkpoint saves it: {use, checked}.
std::array<std::int64_t, 2> dropped_use_pair(const SparseLdlt& solver) {
  switch (solver.dropped_use()) {
    case SparseLdlt::DroppedUse::usable:
      return {1, 1};
    case SparseLdlt::DroppedUse::unusable:
      return {0, 1};
    case SparseLdlt::DroppedUse::unchecked:
      break;
  }
  return {1, 0};
}

/// The inverse of dropped_use_pair().
void set_dropped_use(SparseLdlt& solver, std::int64_t use, std::int64_t checked) {
  solver.set_dropped_use(checked == 0 ? SparseLdlt::DroppedUse::unchecked
                         : use != 0   ? SparseLdlt::DroppedUse::usable
                                      : SparseLdlt::DroppedUse::unusable);
}

}  // namespace

template <int D>
void Solver<D>::save_state(Checkpoint& c) const {
  const auto& P = particles;
  c.reals["solver.position"] = flatten(P.position);
  c.reals["solver.velocity"] = flatten(P.velocity);
  c.reals["solver.affine"] = flatten(P.affine);
  c.reals["solver.deformation_gradient"] = flatten(P.deformation_gradient);
  c.reals["solver.stress"] = flatten(P.stress);
  std::vector<double> state;
  for (const PointState& s : P.state) {
    state.push_back(s.stress_zz);
    state.push_back(s.plastic_strain);
  }
  c.reals["solver.point_state"] = std::move(state);
  c.reals["solver.mass"] = P.mass;
  c.reals["solver.volume0"] = P.volume0;
  c.reals["solver.half_width"] = P.half_width;
  c.integers["solver.material"].assign(P.material.begin(), P.material.end());
  c.integers["solver.body"].assign(P.body.begin(), P.body.end());
  c.reals["solver.wall_impulse"] = flatten(wall_impulse_);
  c.reals["solver.max_speed"] = {max_speed_};
  for (std::size_t i = 0; i < dual_.size(); ++i) {
    const EnhancedState<D>& e = dual_[i].enh;
    const std::string key = "solver.enhanced_" + std::to_string(i) + ".";
    const auto& s = e.previous_state;
    c.integers["solver.enhanced_state_" + std::to_string(i)].assign(s.begin(), s.end());
    c.integers[key + "factored"] = {e.schur_factored ? 1 : 0, e.kkt_factored ? 1 : 0};
    const auto schur_dropped = dropped_use_pair(*e.schur_solver);
    const auto kkt_dropped = dropped_use_pair(*e.kkt_solver);
    c.integers[key + "dropped"] = {schur_dropped[0], schur_dropped[1], kkt_dropped[0],
                                   kkt_dropped[1]};
    const bool bordered = e.bordered_factor == e.kkt_solver->factorizations();
    c.integers[key + "bordered_rows"] = {bordered ? static_cast<std::int64_t>(e.bordered_rows)
                                                  : std::int64_t{0}};
    c.integers[key + "kkt_signature"].assign(e.kkt_signature.begin(), e.kkt_signature.end());
    c.integers[key + "kkt_alpha_cols"].assign(e.kkt_alpha_cols.begin(), e.kkt_alpha_cols.end());
    // Where the next steps' refinement starts (the last two solutions and their unknowns).
    for (std::size_t r = 0; r < e.recent_solution.size(); ++r) {
      const std::string slot = std::to_string(r);
      const Eigen::VectorXd& x = e.recent_solution[r];
      c.reals[key + "recent_solution_" + slot].assign(x.data(), x.data() + x.size());
      c.integers[key + "recent_signature_" + slot].assign(e.recent_signature[r].begin(),
                                                          e.recent_signature[r].end());
      c.integers[key + "recent_columns_" + slot].assign(e.recent_columns[r].begin(),
                                                        e.recent_columns[r].end());
    }
    if (e.schur_factored) save_factorised(c, key + "schur", e.schur_base, *e.schur_solver);
    if (e.kkt_factored) save_factorised(c, key + "kkt", e.kkt_base, *e.kkt_solver);
    // Mortar / one-way: the Schur complement the factorisation in hand is of.
    const std::string phi = "solver.coupling_" + std::to_string(i) + ".";
    c.integers[phi + "factored"] = {dual_[i].schur_factored ? 1 : 0,
                                    static_cast<std::int64_t>(dual_[i].factored_structure),
                                    dual_[i].refine_wait, dual_[i].refine_backoff};
    const auto phi_dropped = dropped_use_pair(*dual_[i].schur);
    c.integers[phi + "dropped"] = {phi_dropped[0], phi_dropped[1]};
    if (dual_[i].schur_factored) {
      save_factorised(c, phi + "schur", dual_[i].schur_base, *dual_[i].schur);
    }
    // Where the next solves of each kind start CG (the hashes as their bits).
    auto save_lambdas = [&](const std::string& which, const auto& lambdas,
                            const auto& lambda_structures) {
      auto& structures = c.integers[phi + which + "_structure"];
      structures.clear();
      for (std::size_t kind = 0; kind < lambdas.size(); ++kind) {
        const NodeBlock<D>& lambda = lambdas[kind];
        c.reals[phi + which + "_lambda_" + std::to_string(kind)].assign(
            lambda.data(), lambda.data() + lambda.size());
        structures.push_back(static_cast<std::int64_t>(lambda_structures[kind]));
      }
    };
    save_lambdas("last", dual_[i].last_lambda, dual_[i].last_structure);
    save_lambdas("earlier", dual_[i].earlier_lambda, dual_[i].earlier_structure);
  }
}

template <int D>
void Solver<D>::restore_state(const Checkpoint& c) {
  auto& P = particles;
  const std::size_t n = P.size();
  const auto d = static_cast<std::size_t>(D);
  unflatten(c.real("solver.position", n * d), P.position);
  unflatten(c.real("solver.velocity", n * d), P.velocity);
  unflatten(c.real("solver.affine", n * d * d), P.affine);
  unflatten(c.real("solver.deformation_gradient", n * d * d), P.deformation_gradient);
  unflatten(c.real("solver.stress", n * d * d), P.stress);
  const std::vector<double>& state = c.real("solver.point_state", 2 * n);
  for (std::size_t p = 0; p < n; ++p) P.state[p] = {state[2 * p], state[2 * p + 1]};
  P.mass = c.real("solver.mass", n);
  P.volume0 = c.real("solver.volume0", n);
  P.half_width = c.real("solver.half_width", n);
  const auto& material = c.integer("solver.material", n);
  const auto& body = c.integer("solver.body", n);
  for (std::size_t p = 0; p < n; ++p) {
    P.material[p] = static_cast<int>(material[p]);
    P.body[p] = static_cast<int>(body[p]);
  }
  unflatten(c.real("solver.wall_impulse", 3 * wall_impulse_.size()), wall_impulse_);
  max_speed_ = c.real("solver.max_speed", 1)[0];
  locate_limit_.clear();  // the particles moved: the next step looks at every one
  for (std::size_t i = 0; i < dual_.size(); ++i) {
    EnhancedState<D>& e = dual_[i].enh;
    const auto& s = c.integer("solver.enhanced_state_" + std::to_string(i));
    e.previous_state.assign(s.begin(), s.end());
    // The factorisations the run had in hand, made again from the same matrices.
    const std::string key = "solver.enhanced_" + std::to_string(i) + ".";
    const auto& factored = c.integer(key + "factored", 2);
    const auto& signature = c.integer(key + "kkt_signature");
    e.kkt_signature.assign(signature.begin(), signature.end());
    // (Absent from a checkpoint written before it was kept: the first contact step then forms
    // its matrix and factorises it unless its pattern is the saved one's.)
    e.kkt_alpha_cols.clear();
    if (const auto it = c.integers.find(key + "kkt_alpha_cols"); it != c.integers.end()) {
      e.kkt_alpha_cols.assign(it->second.begin(), it->second.end());
    }
    // Where the next steps' refinement starts (absent from a checkpoint written before it was
    // kept: from the factor's answer until two solves have the same unknowns).
    for (std::size_t r = 0; r < e.recent_solution.size(); ++r) {
      const std::string slot = std::to_string(r);
      e.recent_solution[r].resize(0);
      e.recent_signature[r].clear();
      e.recent_columns[r].clear();
      const auto x = c.reals.find(key + "recent_solution_" + slot);
      if (x == c.reals.end()) continue;
      const auto& rows = c.integer(key + "recent_signature_" + slot);
      const auto& columns = c.integer(key + "recent_columns_" + slot);
      if (x->second.size() != rows.size() + columns.size() * d) {
        throw std::runtime_error(key + "recent_solution_" + slot + ": expected " +
                                 std::to_string(rows.size() + columns.size() * d) + " values");
      }
      e.recent_solution[r] = Eigen::Map<const Eigen::VectorXd>(
          x->second.data(), static_cast<Eigen::Index>(x->second.size()));
      e.recent_signature[r].assign(rows.begin(), rows.end());
      e.recent_columns[r].assign(columns.begin(), columns.end());
    }
    auto refactorise = [&](const std::string& name, Eigen::SparseMatrix<double>& base,
                           SparseLdlt& solver, std::size_t& pattern, bool& ok) {
      base = restore_factorised(c, name, solver);
      pattern = pattern_hash(base);
      ok = true;
    };
    if (factored[0] != 0) {
      refactorise(key + "schur", e.schur_base, *e.schur_solver, e.schur_pattern, e.schur_factored);
    }
    if (factored[1] != 0) {
      refactorise(key + "kkt", e.kkt_base, *e.kkt_solver, e.kkt_pattern, e.kkt_factored);
    }
    // Whether their refinement reads L's dropped copy (absent from a checkpoint written before
    // it could: all of L until the next factorisation checks its copy).
    if (const auto it = c.integers.find(key + "dropped"); it != c.integers.end()) {
      if (it->second.size() != 4) throw std::runtime_error(key + "dropped: expected 4 values");
      set_dropped_use(*e.schur_solver, it->second[0], it->second[1]);
      set_dropped_use(*e.kkt_solver, it->second[2], it->second[3]);
    }
    // The rows bordered so far on the factorisation in hand (absent: none).
    e.bordered_factor = e.kkt_solver->factorizations();
    e.bordered_rows = 0;
    if (const auto it = c.integers.find(key + "bordered_rows"); it != c.integers.end()) {
      if (it->second.size() != 1 || it->second[0] < 0) {
        throw std::runtime_error(key + "bordered_rows: expected 1 count");
      }
      e.bordered_rows = static_cast<std::size_t>(it->second[0]);
    }
    DualWall<D>& w = dual_[i];
    const std::string phi = "solver.coupling_" + std::to_string(i) + ".";
    const auto& coupling = c.integer(phi + "factored", 4);
    w.schur_factored = false;
    w.support_recorded = false;  // the next step assembles its coupling in full
    w.factored_structure = static_cast<std::size_t>(coupling[1]);
    w.refine_wait = static_cast<int>(coupling[2]);
    w.refine_backoff = static_cast<int>(coupling[3]);
    if (coupling[0] != 0) {
      refactorise(phi + "schur", w.schur_base, *w.schur, w.pattern_hash, w.schur_factored);
    }
    // Where the next solves of each kind start CG (absent from a checkpoint written before they
    // were kept: from the factor's answer, or not extrapolated, until solves of the kind have
    // found their multipliers).
    auto restore_lambdas = [&](const std::string& which, auto& lambdas, auto& lambda_structures) {
      for (std::size_t kind = 0; kind < lambdas.size(); ++kind) {
        lambdas[kind].resize(0, D);
        lambda_structures[kind] = 0;
      }
      const auto it = c.integers.find(phi + which + "_structure");
      if (it == c.integers.end()) return;
      if (it->second.size() != lambdas.size()) {
        throw std::runtime_error(phi + which + "_structure: expected " +
                                 std::to_string(lambdas.size()) + " values");
      }
      for (std::size_t kind = 0; kind < lambdas.size(); ++kind) {
        const std::string name = phi + which + "_lambda_" + std::to_string(kind);
        const auto found = c.reals.find(name);
        if (found == c.reals.end() || found->second.size() % d != 0) {
          throw std::runtime_error(name + ": expected a multiple of " + std::to_string(d) +
                                   " values");
        }
        lambdas[kind].resize(static_cast<Eigen::Index>(found->second.size() / d), D);
        std::copy(found->second.begin(), found->second.end(), lambdas[kind].data());
        lambda_structures[kind] = static_cast<std::size_t>(it->second[kind]);
      }
    };
    restore_lambdas("last", w.last_lambda, w.last_structure);
    restore_lambdas("earlier", w.earlier_lambda, w.earlier_structure);
    // Which copy of L CG reads (absent from a checkpoint written before there was a choice:
    // the dropped one).
    w.schur->set_dropped_use(SparseLdlt::DroppedUse::usable);
    if (const auto it = c.integers.find(phi + "dropped"); it != c.integers.end()) {
      if (it->second.size() != 2) throw std::runtime_error(phi + "dropped: expected 2 values");
      set_dropped_use(*w.schur, it->second[0], it->second[1]);
    }
  }
}

std::unique_ptr<Simulation> make_simulation(const Scene& scene) {
  switch (scene.dimension) {
    case 1:
      return std::make_unique<Solver<1>>(scene);
    case 2:
      return std::make_unique<Solver<2>>(scene);
    default:
      return std::make_unique<Solver<3>>(scene);
  }
}

template class Solver<1>;
template class Solver<2>;
template class Solver<3>;

}  // namespace mpm
