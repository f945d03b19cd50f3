#pragma once
// A scene: everything `mpm run` needs, read from JSON and validated key by key. Any problem is a
// SceneError whose message is one line: "FILE: /json/path: what was expected".

#include <filesystem>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <nlohmann/json_fwd.hpp>

#include "mpm/material.hpp"
#include "mpm/shape.hpp"
#include "mpm/walls.hpp"

namespace mpm {

class SceneError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

enum class UpdateScheme { usl, musl, mls };
enum class Transfer { flip, apic };  ///< flip with flip_blend = 0 is PIC

struct MaterialSpec {
  std::string name;
  Material model;
};

struct BodySpec {
  enum class Shape { box, sphere, mesh };
  std::string name;
  int material = 0;
  Shape shape = Shape::box;
  Eigen::VectorXd min, max;  ///< box corners (dim), before any rotation
  /// Box rotation about its centre (identity unless "rotation" is given: an angle in degrees in
  /// 2D, angles about x, y, z in 3D). A rotated box is seeded on a lattice aligned with its own
  /// edges, so its faces are flat (a block resting on an inclined wall).
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();
  /// Seeded on the box's own lattice: rotated, or "lattice": "body" (a box or segment whose
  /// faces must sit exactly at min/max, e.g. a bar flush against a wall between grid nodes).
  bool own_lattice = false;
  /// Mesh bodies (3D): the particle positions that fill the closed surface, one per sub-cell
  /// centre inside it (found when the scene is read, so a bad mesh fails against its key).
  Eigen::MatrixX3d points;
  Eigen::VectorXd center;  ///< sphere/disk centre (dim)
  double radius = 0.0;
  int particles_per_cell = 2;  ///< per direction
  Eigen::VectorXd velocity;    ///< initial velocity (dim)
  /// Optional standing-wave initial velocity added to `velocity`:
  /// v(x) += amplitude * sin(wavenumber * (x[axis] - origin)), e.g. a vibration mode.
  struct SineVelocity {
    Eigen::VectorXd amplitude;
    double wavenumber = 0.0;
    int axis = 0;
    double origin = 0.0;
  };
  std::optional<SineVelocity> velocity_sine;
  Eigen::VectorXd body_force;  ///< acceleration added to gravity (dim)
};

struct BoundaryPackage;

/// How a dual-grid wall couples its boundary grid to the standard grid (DESIGN.md section 4).
enum class CouplingMethod {
  one_way,   ///< as published: boundary grid first, its velocity prescribed on Phi for the bulk
  mortar,    ///< two-way saddle point on Phi: equal and opposite interface forces
  enhanced,  ///< Enhanced velocity field: v = v^A + v^alpha, wall multipliers on Gamma
  sdf,       ///< baseline: signed distance on the standard grid, nodes behind the wall constrained
};

/// A wall represented by a boundary grid (a layer along the surface) coupled to the standard
/// grid by Lagrange multipliers on the interface Phi (the Blending method).
struct DualWallSpec {
  std::string name;
  WallContact contact;
  /// The condition on each part of the layer (package->layer.part_names order, one entry when
  /// it names none): the wall's own (contact.condition) unless the scene's "parts" gives that
  /// part another (a terrain and the barrier standing on it are one mesh, with different
  /// friction). The scene reader fills it.
  std::vector<WallCondition> part_condition;
  [[nodiscard]] const WallCondition& condition(int part) const {
    return part_condition[static_cast<std::size_t>(part)];
  }
  CouplingMethod method = CouplingMethod::mortar;
  /// Blending walls: Phi's multipliers within this many cell spacings of each other along the
  /// surface are merged into one (0: one per Phi node, as the coupling is built).
  double multiplier_radius = 0.0;
  /// Blending walls ("corners": "facets", their default): a Gamma node where facets meet at a
  /// concave corner or crease is held against each facet (walls.hpp,
  /// constrain_velocity_in_corner) rather than along its own normal, their average, which lets
  /// material slide into one of them ("normal"). Enhanced and sdf walls: false.
  bool corner_facets = false;
  /// Layer, coupling matrices and cell flags, built while the scene is read (from a point in
  /// 1D, a polyline in 2D, a mesh or a package from `mpm prep` in 3D).
  std::shared_ptr<const BoundaryPackage> package;
};

/// The standard grid's storage (mpm::Grid): dense over the box, sparse by blocks with memory
/// only where particles have been, or chosen from the bodies (sparse when their blocks are
/// less than half of the box's).
enum class GridStorage { automatic, dense, sparse };

struct Scene {
  std::filesystem::path file;  ///< where it came from, for messages ("<memory>" otherwise)
  std::string name;
  int dimension = 3;
  Eigen::VectorXd box_min, box_max;  ///< the grid box; walls sit on its faces
  double spacing = 0.0;
  /// The refinement `mpm run --resolution K` applied: the file's spacing (and fixed dt) / K.
  int resolution = 1;
  GridStorage grid_storage = GridStorage::automatic;
  ShapeKind shape = ShapeKind::bspline2;
  UpdateScheme update = UpdateScheme::musl;
  Transfer transfer = Transfer::apic;
  double flip_blend = 1.0;  ///< FLIP fraction of the PIC/FLIP blend
  double mass_threshold = 1e-9;
  /// Nodes lighter than this times the mean particle mass take no part in the Phi coupling of
  /// dual-grid walls: a multiplier would push them by gap / R_J, unbounded as the sliver of
  /// mass that reaches them vanishes (DESIGN.md section 4).
  double coupling_mass_threshold =
      1e-2;  ///< nodes lighter than this times the mean particle mass are inactive
  /// Blending walls (mortar, one-way): the Phi coupling's multipliers are solved until the two
  /// grids' interface velocities agree to this fraction of their size (or the multipliers are
  /// this close to exact). They are impulses applied equal and opposite to the two grids, so
  /// momentum is exact whatever their error, and the step's kinetic energy differs from the
  /// exact projection's only to second order in it (docs/blending.md, "The coupling's
  /// tolerance"). Enhanced walls: their contact system, refined against an earlier
  /// factorisation, to this fraction of its unknowns' size, the impulses counted as the
  /// velocities they give the standard grid (docs/enhanced.md).
  double coupling_tolerance = 1e-6;
  /// Enhanced walls: a boundary node whose effective mass after the standard grid is eliminated
  /// (K_SS = m^alpha_S - sum_I (m^{A,alpha}_IS)^2 / m^A_I) is below this fraction of its own
  /// mass is nearly a combination of standard-grid functions: its enhancement is dropped.
  double dependence_tolerance = 0.01;
  /// Enhanced walls: drop the enhancement at Gamma nodes where every standard node the wall's
  /// multipliers reach carries mass (the standard field alone can take the wall value there).
  bool drop_covered_enhancement = true;
  Eigen::VectorXd gravity;
  double end_time = 0.0;
  double cfl = 0.5;
  std::optional<double> fixed_dt;  ///< set: fixed step; unset: adaptive from the CFL number
  double output_interval = 0.0;
  double history_interval = 0.0;  ///< 0: every step
  /// Deposit depths (m) at which summary.json reports a run-out: the furthest any particle
  /// travelled among those where the deposit is at least that deep (output.runout_depths;
  /// empty: the file's spacing, spacing x resolution, which `--resolution` does not change).
  std::vector<double> runout_depths;
  /// Dual-grid walls (or parts) whose retained volume summary.json reports: the particle volume
  /// on the source side of the vertical plane through the wall's centre that faces the source.
  struct RetainingWall {
    std::string name;  ///< as the scene gives it: "wall" or "wall_part"
    int wall = 0;      ///< index into dual_walls
    int part = -1;     ///< the part of the layer, -1: the whole wall
  };
  std::vector<RetainingWall> retaining_walls;
  std::vector<MaterialSpec> materials;
  std::vector<BodySpec> bodies;
  std::vector<BoxWall> walls;
  std::vector<DualWallSpec> dual_walls;
};

/// Parses and validates a scene file. Throws SceneError. resolution K > 1 refines it first:
/// grid spacing and a fixed time step divided by K (particles per cell, and so the particles'
/// spacing, follow the grid; widths given in cells, such as a wall's default thickness of h,
/// follow too), and each dual-grid wall's package cache is kept apart ("name_rK.h5").
Scene load_scene(const std::filesystem::path& file, int resolution = 1);
/// Same for an in-memory document; `origin` names it in messages.
Scene parse_scene(const nlohmann::json& doc, const std::filesystem::path& origin);

/// Explicit viscous step limit rho size^2 / (2 D mu_max) over the scene's materials (CFL number
/// 1; infinite when none is viscous).
double viscous_dt_limit(const Scene& scene, double size);

/// Largest wave speed over the scene's materials at the reference state.
double max_wave_speed(const Scene& scene);

}  // namespace mpm
