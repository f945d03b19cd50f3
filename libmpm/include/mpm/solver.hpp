#pragma once
// The explicit MPM solver on the standard grid, templated on the dimension. A step reads like
// the algorithm:
//
//   particles_to_grid(dt);      // mass, momentum, internal and external force (MLS-MPM:
//                               // the momentum after the force, p_I + dt f_I)
//   update_grid(dt);            // v_I^{n+1} = (p_I + dt f_I) / m_I
//   apply_walls();              // wall conditions on the box faces and on the Gamma nodes
//   grid_to_particles(dt);      // dual-grid walls: multipliers on Phi tie the two grids (on one
//                               // core, while the other gathers the particles they cannot
//                               // reach); v_p, x_p (PIC/FLIP or APIC); MUSL remap; stress
//
// make_simulation() hides the dimension behind the Simulation interface for the run loop.

#include <array>
#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "mpm/checkpoint.hpp"
#include "mpm/dual_grid.hpp"
#include "mpm/grid.hpp"
#include "mpm/output.hpp"
#include "mpm/particles.hpp"
#include "mpm/scene.hpp"

namespace mpm {

struct Energies {
  double kinetic = 0.0;
  double strain = 0.0;
  double gravity = 0.0;  ///< -sum m g.x (body forces are not potential energy)
  [[nodiscard]] double total() const { return kinetic + strain + gravity; }
};

/// Wall-clock seconds spent in each phase of the steps so far (steady clock, summed). The
/// phases partition step(): locate (which particles are in a boundary layer, and where),
/// particles to grid (binning and scatter, both grids), grid update, walls (box, sdf and Gamma
/// conditions), coupling (the Phi and Enhanced solves, the remap's included: their own
/// duration, as they run beside the gather, taken from the gather's time),
/// grid to particles (gather, MUSL remap, velocity gradients), stress (the constitutive update),
/// advect (move and check the particles).
struct PhaseTimes {
  double locate = 0.0;
  double particles_to_grid = 0.0;
  double grid_update = 0.0;
  double walls = 0.0;
  double coupling = 0.0;
  double grid_to_particles = 0.0;
  double stress = 0.0;
  double advect = 0.0;
  [[nodiscard]] double total() const {
    return locate + particles_to_grid + grid_update + walls + coupling + grid_to_particles +
           stress + advect;
  }
};

/// The work of one dual-grid wall's coupling since the solver was made (not restored from a
/// checkpoint): what the Phi (Blending) or Gamma (Enhanced) system is made of and how often it
/// was factorised or solved by refinement against an earlier factorisation.
struct CouplingWork {
  std::string wall;
  std::string method;
  std::size_t surface_nodes = 0;  ///< multiplier nodes of the surface (Phi or Gamma)
  std::size_t multipliers = 0;    ///< after merging ("multiplier_radius"; Blending only)
  /// Gamma nodes at concave corners and creases, held against each of their facets (Blending)
  std::size_t corner_nodes = 0;
  std::size_t factorizations = 0;
  std::size_t refinement_passes = 0;
  /// Blending: steps in which the nodes the Phi coupling joins changed (nodes crossing the
  /// coupling threshold): its matrices took a new shape, solved against the factorisation in
  /// hand when the same multipliers are active.
  std::size_t reshaped_steps = 0;
  /// Blending: steps that kept the coupling in hand without assembling it (its carried
  /// multipliers and their supports' nodes on the same side of the mass threshold as when it
  /// was assembled: a resting layer).
  std::size_t kept_steps = 0;
  /// Enhanced: the contact active set's passes, the steps it had not settled after 30 (their
  /// last pass's states stand), and the re-additions refused to a multiplier released twice in
  /// a step (its gap closing again: the loop would alternate; docs/enhanced.md).
  std::size_t active_set_passes = 0, unsettled_steps = 0, kept_released = 0;
  /// Where the coupling's time went (wall clock, seconds): forming the active coupling and
  /// its matrices, ordering them for factorisation (the fill-reducing analysis, when the
  /// pattern is new), factorising them, and solving (refinement included). The coupling runs
  /// beside the free particles' gather, so these can add up to more than the coupling phase.
  /// (S formed again after a refinement that failed counts with the solves; a resumed run's
  /// factorisations include those of the saved matrices it refactorises.)
  double assembly_seconds = 0.0;
  double analysis_seconds = 0.0;
  double factorization_seconds = 0.0;
  double solve_seconds = 0.0;
};

/// The standard grid's memory (bytes over its five node arrays), sampled every 16 steps.
struct GridMemory {
  std::size_t nodes = 0;           ///< nodes in the scene's box (ghost layers included)
  std::size_t box_bytes = 0;       ///< what the box would take stored densely
  std::size_t peak_bytes = 0;      ///< the most the arrays held (pages backed by memory)
  std::size_t active_at_peak = 0;  ///< what the active blocks' nodes needed then
  std::size_t peak_active = 0;     ///< the most the active blocks needed
};

/// Dimension-independent face of a solver, used by the run loop and the command line.
class Simulation {
 public:
  virtual ~Simulation() = default;
  [[nodiscard]] virtual int dimension() const = 0;
  [[nodiscard]] virtual std::size_t particle_count() const = 0;
  /// The CFL-limited step for the current state: cfl * h / max(c + |v_p|).
  [[nodiscard]] virtual double stable_dt(double cfl) const = 0;
  virtual void step(double dt) = 0;
  [[nodiscard]] virtual Energies energies() const = 0;
  [[nodiscard]] virtual Eigen::Vector3d momentum() const = 0;
  /// Impulse the walls gave the material since the last reset, one entry per scene wall.
  [[nodiscard]] virtual const std::vector<Eigen::Vector3d>& wall_impulses() const = 0;
  virtual void reset_wall_impulses() = 0;
  /// Names of the entries of wall_impulses(): box faces, then each dual wall (per part when it
  /// has several).
  [[nodiscard]] virtual std::vector<std::string> wall_names() const = 0;
  [[nodiscard]] virtual ParticleFrame frame(double time, std::int64_t step) const = 0;
  /// Set when the last step produced a non-finite value, an inverted element or a particle
  /// outside the grid: names the particle, its material and the quantity.
  [[nodiscard]] virtual const std::optional<std::string>& fault() const = 0;
  /// Everything the next step reads that the scene does not give (particle state, wall
  /// impulses since the last history row, the largest particle speed, Enhanced contact states),
  /// under "solver.*" keys.
  virtual void save_state(Checkpoint& checkpoint) const = 0;
  /// The inverse of save_state(); throws std::runtime_error naming the key that does not fit
  /// this scene.
  virtual void restore_state(const Checkpoint& checkpoint) = 0;
  /// Time per phase of step() since construction (not restored from a checkpoint).
  [[nodiscard]] virtual const PhaseTimes& phase_times() const = 0;
  /// One entry per dual-grid wall (Blending or Enhanced; sdf walls have no coupling).
  [[nodiscard]] virtual std::vector<CouplingWork> coupling_work() const = 0;
  /// How the dual-grid couplings met the gather, counted over the calls since construction
  /// (Solver::CouplingOverlap; one a step, two under MUSL, whose remap is coupled too; calls in
  /// steps without layer particles are not counted): [0] "after", the coupling first and then
  /// the gather of every particle; [1] "beside", the coupling on one core while the other
  /// gathers the particles it cannot change.
  [[nodiscard]] virtual std::array<std::size_t, 2> coupling_overlap_counts() const = 0;
  [[nodiscard]] virtual GridMemory grid_memory() const = 0;
};

std::unique_ptr<Simulation> make_simulation(const Scene& scene);

template <int D>
class Solver final : public Simulation {
 public:
  static constexpr int pad = kGhostLayers;

  explicit Solver(const Scene& scene);

  [[nodiscard]] int dimension() const override { return D; }
  [[nodiscard]] std::size_t particle_count() const override { return particles.size(); }
  [[nodiscard]] double stable_dt(double cfl) const override;
  void step(double dt) override;
  [[nodiscard]] Energies energies() const override;
  [[nodiscard]] Eigen::Vector3d momentum() const override;
  [[nodiscard]] const std::vector<Eigen::Vector3d>& wall_impulses() const override {
    return wall_impulse_;
  }
  void reset_wall_impulses() override;
  [[nodiscard]] std::vector<std::string> wall_names() const override;
  [[nodiscard]] ParticleFrame frame(double time, std::int64_t step) const override;
  [[nodiscard]] const std::optional<std::string>& fault() const override { return fault_; }
  void save_state(Checkpoint& checkpoint) const override;
  void restore_state(const Checkpoint& checkpoint) override;
  [[nodiscard]] const PhaseTimes& phase_times() const override { return times_; }
  [[nodiscard]] std::vector<CouplingWork> coupling_work() const override;
  [[nodiscard]] GridMemory grid_memory() const override {
    return {grid.node_count(), grid.box_bytes(), grid.peak_committed, grid.active_at_peak,
            grid.peak_active};
  }

  // The phases of a step, public so tests can check each one.
  /// dt: MLS-MPM scatters the momentum after the force, p_I + dt f_I (scatter()).
  void particles_to_grid(double dt);
  void update_grid(double dt);
  void apply_walls();
  /// Couples the dual-grid walls (layer_couple(): before the gather, or beside the gather of the
  /// particles whose stencils reach no node a coupling changes), then gathers the rest.
  void grid_to_particles(double dt);

  /// The dual-grid walls (Blending and Enhanced), in scene order.
  [[nodiscard]] const std::vector<DualWall<D>>& dual_walls() const { return dual_; }
  /// Which particles each layer holds; run by particles_to_grid(), public for tests.
  void locate_in_layers();
  /// Per particle, this step: 1 where its stencil may reach a node a coupling changes (its
  /// cell's, locate_in_layers()); empty without dual-grid walls. Public for tests.
  [[nodiscard]] const std::vector<std::uint8_t>& near_coupling() const { return near_coupling_; }

  /// How a dual-grid step's coupling meets the gather of the particles it cannot change
  /// (couple_beside()): beside it, on the other core, or after it, all particles in one pass
  /// then; by default whichever of the two has lately taken less time (the answers are the same
  /// bit for bit either way).
  enum class CouplingOverlap { adaptive, beside, after };
  void set_coupling_overlap(CouplingOverlap mode) { overlap_mode_ = mode; }
  /// How many times each way ran: [0] after the coupling, [1] beside it.
  [[nodiscard]] std::array<std::size_t, 2> coupling_overlap_counts() const override {
    return {overlap_[0].runs[0] + overlap_[1].runs[0], overlap_[0].runs[1] + overlap_[1].runs[1]};
  }

  /// locate_in_layers() skips the particles that cannot have reached a layer's or a coupling's
  /// cells since it last looked at them (the same answers); `false` looks at every particle
  /// every step (tests compare the two). locate_skipped(): particle-steps skipped so far.
  /// How far a particle can have gone is what step() moved it (or restore_state() resets it):
  /// code that moves `particles` by hand between steps turns skipping off for the next step.
  void set_locate_skipping(bool on) { locate_skipping_ = on; }
  [[nodiscard]] std::size_t locate_skipped() const { return locate_skipped_; }

  /// Index range [begin, end) of the particles of each material.
  [[nodiscard]] const std::vector<std::pair<std::size_t, std::size_t>>& material_groups() const {
    return groups_;
  }

  Particles<D> particles;
  Grid<D> grid;

 private:
  /// Which particles a gather pass takes: all, or those whose stencils reach no node a
  /// coupling may change (free: gathered while the coupling runs), or the others (near).
  enum class Reach { all, free, near };
  [[nodiscard]] bool takes(Reach reach, std::size_t p) const {
    return reach == Reach::all || (near_coupling_[p] != 0) == (reach == Reach::near);
  }
  template <class Shape>
  void scatter(bool with_force, double dt);
  template <class Shape>
  void scatter_factorised(const Stencil<D, Shape>& st, double m, const double (&v)[D],
                          const double (&C)[D][D], const double (*body_force)[D],
                          const double (*stress)[D][D], bool mls, bool fold, double dt);
  /// layer_couple(remapped) and pass(Reach): the coupling on one core beside pass(free), then
  /// pass(near), where a wall has layer particles this step; else pass(all).
  template <class Pass>
  void couple_beside(bool remapped, Pass&& pass);
  template <class Shape>
  void gather(double dt, Reach reach);
  template <class Shape>
  void gather_velocity_gradient(double dt, Reach reach);
  template <class Sample>
  void sample_and_update_stress(double dt, Sample&& sample);
  /// For sample_and_update_stress(): the standard grid's velocity gradient at particle p goes to
  /// L for the update now (true), or, for a particle an Enhanced layer also moves, to its layer
  /// list entry, where the layer's part is added before its update (false).
  bool take_gradient(std::size_t p, const Mat<D>& gradient, Mat<D>& L) {
    if (particles.layer_wall[p] >= 0) {
      layer_gradient_[static_cast<std::size_t>(particles.layer_slot[p])] = gradient;
      return false;
    }
    L = gradient;
    return true;
  }
  /// f(node) for every node of the grid's active blocks, in parallel.
  template <class F>
  void for_each_active_node(F&& f);
  void update_layer_stress(double dt);
  void constrain_walls(NodeField<Vec<D>>& velocity, bool record);
  // Dual-grid (boundary-grid) counterparts of the phases, in dual_grid.cpp.
  void setup_dual_walls();
  void layer_scatter(bool with_force);
  void layer_update(double dt);
  void layer_walls(std::vector<Vec<D>> DualWall<D>::*velocity, bool record);
  void layer_couple(bool remapped);
  bool factorise_schur(DualWall<D>& w, bool mortar, SparseLdlt::Order order);
  void layer_gather(double dt);
  void layer_gather_gradient();
  void layer_remap();
  // The Enhanced velocity field walls, in enhanced.cpp.
  void enhanced_assemble(DualWall<D>& w);
  void enhanced_solve(DualWall<D>& w, NodeField<Vec<D>>& va,
                      const std::vector<Vec<D>>& alpha_momentum, std::vector<Vec<D>>& valpha,
                      bool constrained, bool record);
  /// Does the gather read the old grid velocities v_I^n (FLIP's increment v^{n+1} - v^n)? PIC
  /// and APIC gather v^{n+1} alone.
  [[nodiscard]] bool flip_increment() const {
    return scene_.transfer != Transfer::apic && scene_.flip_blend > 0.0;
  }
  /// Does the scatter add dt f_I to the momentum (MLS-MPM, where nothing reads v_I^n)?
  [[nodiscard]] bool force_in_momentum() const {
    return scene_.update == UpdateScheme::mls && !flip_increment();
  }
  /// Does the layer own a particle it holds (Blending), or only enhance it (Enhanced)?
  [[nodiscard]] bool owned_by_layer(std::size_t p) const {
    return particles.layer_wall[p] >= 0 && !dual_[particles.layer_wall[p]].enhanced;
  }
  void advect_and_check(double dt);
  void setup_sdf_wall(const DualWallSpec& spec);
  void constrain_sdf_walls(NodeField<Vec<D>>& velocity, bool record);
  void fill_bodies();
  /// Grid storage for the scene (GridStorage): resizes the grid, after fill_bodies().
  void choose_grid_storage();
  void bin_particles_into_slabs();

  Scene scene_;
  Vec<D> gravity_;
  std::vector<Vec<D>> body_acceleration_;  ///< gravity + body force, per body
  std::vector<std::pair<std::size_t, std::size_t>> groups_;
  std::vector<std::vector<int>> wall_nodes_;  ///< grid nodes on or beyond each wall, by block
  /// Runs of wall_nodes_ / wall_ghosts_ in one grid block (the step skips idle blocks).
  struct BlockRun {
    int block, begin, end;
  };
  std::vector<std::vector<BlockRun>> wall_node_runs_, wall_ghost_runs_;
  /// f(k) for each index k of the runs whose grid block is active this step.
  template <class F>
  void for_each_in_active_blocks(const std::vector<BlockRun>& runs, F&& f) const {
    for (const BlockRun& run : runs) {
      if (grid.block_active[static_cast<std::size_t>(run.block)] == 0) continue;
      for (int k = run.begin; k < run.end; ++k) f(static_cast<std::size_t>(k));
    }
  }
  /// For bonded (non-separable) walls: (ghost node beyond the wall, its mirror image inside).
  std::vector<std::vector<std::pair<int, int>>> wall_ghosts_;
  std::vector<Eigen::Vector3d> wall_impulse_;  ///< box walls, then dual-wall parts
  std::vector<DualWall<D>> dual_;
  /// This step's boundary-layer particles (in index order) and their boundary-grid bases,
  /// computed once by locate_in_layers() for the scatters, gathers and the remap of the step.
  std::vector<int> layer_list_;
  std::vector<AlphaStencil<D>> layer_stencil_;
  /// Per layer particle: its layer cell (its natural coordinates and the map's Jacobian there
  /// go into its basis, layer_stencil_).
  std::vector<int> layer_cell_;
  std::vector<Mat<D>> layer_gradient_;  ///< and its velocity gradient this step
  /// Per layer particle, for layer_scatter() (locate_in_layers() fills them): -V sigma and m b
  /// at the step's start, its point of the isoparametric map (`at`, for the remap's
  /// centroids), and the touch test's reach and the square of its window (separable walls:
  /// compared with squared distances, no square root per pair).
  struct LayerTerms {
    Vec<D> mb, at;
    Mat<D> vs;
    double reach, window_squared;
  };
  std::vector<LayerTerms> layer_terms_;
  /// Per layer particle: its place in its wall's cell order (DualWall::cell_members).
  std::vector<int> layer_place_;
  /// layer_scatter()'s sort by cell stands: every particle is in the layer cell it was in (or
  /// in none, as it was) when the sort was made (locate_in_layers() clears it otherwise).
  bool layer_sort_current_ = false;
  /// locate_in_layers() per chunk of particles: the particles a layer holds (their wall is
  /// P.layer_wall), with their cell, natural coordinates and Jacobian (joined in chunk order, so
  /// the list stays in index order).
  struct LayerHit {
    int particle;
    mpmgeom::LayerLocator::Location at;
  };
  std::vector<std::vector<LayerHit>> layer_hits_;
  std::vector<std::size_t> layer_chunk_first_;  ///< each chunk's first place in the layer list
  /// Per standard-grid cell (locate_in_layers()'s numbering), 1 where the stencil of a particle
  /// in it (nodes c - 1 to c + 2 along each axis, every kernel) may reach a node a dual-grid
  /// wall's coupling changes (setup_dual_walls()); empty without dual-grid walls.
  std::vector<std::uint8_t> coupled_cell_;
  /// Per particle, this step (locate_in_layers()): coupled_cell_ of its cell.
  std::vector<std::uint8_t> near_coupling_;
  /// locate_in_layers() and advect_and_check() take the particles in chunks of this many.
  static constexpr std::size_t kLocateChunk = 1024;
  /// Per standard-grid cell, its distance in cells (the largest of the axes' index
  /// differences, at most 255) to the nearest cell that a dual-grid wall flags or where
  /// coupled_cell_ is set (setup_dual_walls()); empty without dual-grid walls.
  std::vector<std::uint8_t> cell_clearance_;
  /// Per chunk of particles, how far its fastest particle has moved, summed over the steps
  /// (advect_and_check()): no particle of the chunk has moved farther since any earlier step.
  std::vector<double> chunk_travel_;
  /// Per particle, the chunk's travel up to which it stays outside those cells (its travel
  /// when locate_in_layers() last looked at it plus its clearance then), and per chunk the
  /// least of its particles': locate_in_layers() skips them until then.
  std::vector<double> locate_limit_;
  std::vector<double> chunk_limit_;
  bool locate_skipping_ = true;
  std::size_t locate_skipped_ = 0;
  /// couple_beside()'s choice, per call (the gather's, the MUSL remap's): each way's recent
  /// time from the coupling's start to the gather's end ([0] after, [1] beside) and how many
  /// times each ran (couple_beside_next()).
  struct OverlapTimes {
    std::array<double, 2> mean{};
    std::array<std::size_t, 2> runs{};
  };
  std::array<OverlapTimes, 2> overlap_;
  CouplingOverlap overlap_mode_ = CouplingOverlap::adaptive;
  [[nodiscard]] bool couple_beside_next(int call) const;
  /// Signed-distance walls (the baseline): standard-grid nodes on or behind the surface, within
  /// reach of the kernel, with the unit normal into the material at each.
  struct SdfWall {
    const DualWallSpec* spec = nullptr;
    std::vector<int> nodes;
    std::vector<Vec<D>> normal;
    int impulse = 0;  ///< index in wall_impulse_
  };
  std::vector<SdfWall> sdf_;
  /// Particle indices binned by slab of `slab_width` cells along axis 0. Slabs of one parity
  /// never touch the same nodes, so particle-to-grid runs them in parallel without atomics.
  static constexpr int slab_width = 4;
  std::vector<int> slab_order_;
  std::vector<int> slab_start_;
  std::vector<int> slab_of_;
  std::vector<int> slab_count_;  ///< per chunk of particles and slab (bin_particles_into_slabs)
  double mass_threshold_ = 0.0;
  double coupling_threshold_ = 0.0;  ///< absolute, from scene.coupling_mass_threshold
  double max_speed_ = 0.0;
  double step_size_ = 0.0;   ///< smallest cell the CFL condition sees (layer cells count half)
  double wave_speed_ = 0.0;  ///< max_wave_speed(scene)
  double viscous_dt_ = 0.0;  ///< viscous_dt_limit at step_size_ (CFL number 1)
  std::optional<std::string> fault_;
  /// Adds the time since the last lap (or the start of the step) to a phase.
  void lap(double PhaseTimes::*phase) {
    const auto now = std::chrono::steady_clock::now();
    times_.*phase += std::chrono::duration<double>(now - lap_start_).count();
    lap_start_ = now;
  }
  PhaseTimes times_;
  std::chrono::steady_clock::time_point lap_start_ = std::chrono::steady_clock::now();
};

}  // namespace mpm
