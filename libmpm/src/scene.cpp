// Scene loading: nlohmann/json parses, this file validates. Every key is checked for type and
// range, unknown keys are errors, and every message names the file and the JSON path.

#include "mpm/scene.hpp"

#include "mpm/boundary_package.hpp"
#include "mpmgeom/locator.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>

#include <Eigen/Geometry>
#include <fstream>
#include <map>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

namespace mpm {
namespace {

using nlohmann::json;

std::string describe(const json& j) {
  std::string text = j.dump();
  if (text.size() > 40) text = text.substr(0, 37) + "...";
  return text;
}

/// A JSON object being read: remembers which keys were asked for so that finish() can reject
/// the rest (a typo must never silently fall back to a default).
class Reader {
 public:
  Reader(const json& node, std::string path, const std::string& file)
      : node_(node), path_(std::move(path)), file_(file) {
    if (!node_.is_object()) fail("expected an object, got " + describe(node_));
  }

  [[noreturn]] void fail(const std::string& what) const { fail_at(path_, what); }
  [[noreturn]] void fail_at(const std::string& path, const std::string& what) const {
    throw SceneError(file_ + ": " + (path.empty() ? "/" : path) + ": " + what);
  }
  [[nodiscard]] std::string child(const std::string& key) const { return path_ + "/" + key; }
  [[nodiscard]] const std::string& path() const { return path_; }
  [[nodiscard]] const std::string& file() const { return file_; }

  [[nodiscard]] bool has(const std::string& key) {
    known_.insert(key);
    return node_.contains(key);
  }

  const json& required(const std::string& key) {
    if (!has(key)) fail("missing required key '" + key + "'");
    return node_.at(key);
  }

  double number(const std::string& key, std::optional<double> fallback = std::nullopt) {
    if (!has(key)) {
      if (!fallback) fail("missing required key '" + key + "'");
      return *fallback;
    }
    const json& j = node_.at(key);
    if (!j.is_number()) fail_at(child(key), "expected a number, got " + describe(j));
    const double value = j.get<double>();
    if (!std::isfinite(value)) fail_at(child(key), "expected a finite number");
    return value;
  }

  double positive(const std::string& key, std::optional<double> fallback = std::nullopt) {
    const double value = number(key, fallback);
    if (!(value > 0.0)) fail_at(child(key), "expected a positive number, got " + fmt(value));
    return value;
  }

  double in_range(const std::string& key, double lo, double hi, bool open_hi,
                  std::optional<double> fallback = std::nullopt) {
    const double value = number(key, fallback);
    if (value < lo || value > hi || (open_hi && value == hi)) {
      fail_at(child(key), "expected a number in [" + fmt(lo) + ", " + fmt(hi) +
                              (open_hi ? ")" : "]") + ", got " + fmt(value));
    }
    return value;
  }

  int integer(const std::string& key, int lo, int hi, std::optional<int> fallback = std::nullopt) {
    if (!has(key)) {
      if (!fallback) fail("missing required key '" + key + "'");
      return *fallback;
    }
    const json& j = node_.at(key);
    if (!j.is_number_integer()) fail_at(child(key), "expected an integer, got " + describe(j));
    const auto value = j.get<long long>();
    if (value < lo || value > hi) {
      fail_at(child(key), "expected an integer in [" + std::to_string(lo) + ", " +
                              std::to_string(hi) + "], got " + std::to_string(value));
    }
    return static_cast<int>(value);
  }

  bool boolean(const std::string& key, bool fallback) {
    if (!has(key)) return fallback;
    const json& j = node_.at(key);
    if (!j.is_boolean()) fail_at(child(key), "expected true or false, got " + describe(j));
    return j.get<bool>();
  }

  std::string string(const std::string& key, std::optional<std::string> fallback = std::nullopt) {
    if (!has(key)) {
      if (!fallback) fail("missing required key '" + key + "'");
      return *fallback;
    }
    const json& j = node_.at(key);
    if (!j.is_string()) fail_at(child(key), "expected a string, got " + describe(j));
    return j.get<std::string>();
  }

  /// A string that must be one of `choices`.
  std::string choice(const std::string& key, const std::vector<std::string>& choices,
                     std::optional<std::string> fallback = std::nullopt) {
    std::string value = string(key, std::move(fallback));
    for (const auto& c : choices) {
      if (c == value) return value;
    }
    std::string list;
    for (const auto& c : choices) list += (list.empty() ? "" : ", ") + c;
    fail_at(child(key), "expected one of " + list + ", got \"" + value + "\"");
  }

  Eigen::VectorXd vector(const std::string& key, int dim,
                         std::optional<Eigen::VectorXd> fallback = std::nullopt) {
    if (!has(key)) {
      if (!fallback) fail("missing required key '" + key + "'");
      return *fallback;
    }
    const json& j = node_.at(key);
    if (!j.is_array() || static_cast<int>(j.size()) != dim) {
      fail_at(child(key), "expected an array of " + std::to_string(dim) + " numbers (dimension " +
                              std::to_string(dim) + "), got " + describe(j));
    }
    Eigen::VectorXd v(dim);
    for (int d = 0; d < dim; ++d) {
      if (!j[d].is_number() || !std::isfinite(j[d].get<double>())) {
        fail_at(child(key) + "/" + std::to_string(d),
                "expected a finite number, got " + describe(j[d]));
      }
      v[d] = j[d].get<double>();
    }
    return v;
  }

  Reader object(const std::string& key) { return {required(key), child(key), file_}; }

  /// The elements of a non-empty array of objects.
  std::vector<Reader> objects(const std::string& key, bool allow_empty) {
    const json& j = required(key);
    if (!j.is_array()) fail_at(child(key), "expected an array, got " + describe(j));
    if (j.empty() && !allow_empty) fail_at(child(key), "expected at least one entry");
    std::vector<Reader> out;
    for (std::size_t i = 0; i < j.size(); ++i) {
      out.emplace_back(j[i], child(key) + "/" + std::to_string(i), file_);
    }
    return out;
  }

  void finish() const {
    for (const auto& item : node_.items()) {
      if (known_.count(item.key()) == 0) {
        std::string list;
        for (const auto& k : known_) list += (list.empty() ? "" : ", ") + k;
        fail_at(child(item.key()), "unknown key (expected one of: " + list + ")");
      }
    }
  }

  static std::string fmt(double v) {
    std::ostringstream s;
    s << v;
    return s.str();
  }

 private:
  const json& node_;
  std::string path_;
  const std::string& file_;
  std::set<std::string> known_;
};

/// A file named in a scene is relative to the scene's folder.
std::filesystem::path scene_relative(const Scene& scene, const std::string& file) {
  const std::filesystem::path path(file);
  if (path.is_absolute() || scene.file.empty()) return path;
  return scene.file.parent_path() / path;
}

/// Where a mesh goes: "scale", "translate", "rotate" (degrees about x, y, z), for mesh walls and
/// mesh bodies alike.
mpmgeom::ImportOptions read_placement(Reader& r) {
  mpmgeom::ImportOptions import;
  import.scale = r.positive("scale", 1.0);
  import.translation = r.vector("translate", 3, Eigen::VectorXd::Zero(3)).head<3>();
  import.rotation_deg = r.vector("rotate", 3, Eigen::VectorXd::Zero(3)).head<3>();
  return import;
}

Material read_material(Reader& r, int dim) {
  const std::string model = r.choice("model", {"linear_elastic", "neo_hookean", "drucker_prager",
                                               "mu_i", "newtonian_fluid", "bingham"});
  const bool elastic = model == "linear_elastic" || model == "neo_hookean";
  if (!elastic && dim == 1) {
    r.fail_at(r.child("model"), "\"" + model +
                                    "\" needs dimension 2 or 3 (the 1D bar is in "
                                    "uniaxial stress)");
  }
  const double rho = r.positive("density");
  if (model == "newtonian_fluid" || model == "bingham") {
    const double c0 = r.positive("speed_of_sound");
    const double gamma = r.in_range("gamma", 1.0, 20.0, false, 7.0);
    if (gamma == 1.0) r.fail_at(r.child("gamma"), "expected gamma > 1 (Tait exponent), got 1");
    if (model == "newtonian_fluid") {
      const double mu = r.in_range("viscosity", 0.0, 1e12, false, 0.0);
      return NewtonianFluid{rho, c0, gamma, mu};
    }
    return Bingham{rho,
                   c0,
                   gamma,
                   r.in_range("yield_stress", 0.0, 1e12, false),
                   r.in_range("plastic_viscosity", 0.0, 1e12, false),
                   r.positive("regularization", 100.0)};
  }
  const double E = r.positive("youngs_modulus");
  // The 1D bar is in uniaxial stress and does not use nu; 2D/3D need it.
  const double nu =
      dim == 1 ? r.in_range("poisson_ratio", -1.0, 0.5, true, 0.0) : r.number("poisson_ratio");
  if (!(nu > -1.0 && nu < 0.5)) {
    r.fail_at(r.child("poisson_ratio"),
              "expected a Poisson ratio in (-1, 0.5) (0.5 is incompressible: lambda is infinite), "
              "got " +
                  Reader::fmt(nu));
  }
  if (model == "linear_elastic") return LinearElastic{rho, E, nu};
  if (model == "neo_hookean") return NeoHookean{rho, E, nu};
  if (model == "mu_i") {
    // mu(I): the cone through the apex P = 0 with the step's friction mu(I) (DruckerPrager).
    DruckerPrager dp{rho, E, nu, 0.0, 0.0, 0.0, 0.0};
    dp.mu_s = r.in_range("mu_s", 0.0, 10.0, false);
    if (!(dp.mu_s > 0.0)) r.fail_at(r.child("mu_s"), "expected a static friction mu_s > 0");
    dp.mu_2 = r.in_range("mu_2", dp.mu_s, 10.0, false);
    dp.inertial_i0 = r.positive("I_0");
    dp.grain_diameter = r.positive("grain_diameter");
    dp.grain_density = r.positive("grain_density");
    dp.alpha = dp.mu_s / 3.0;
    return dp;
  }
  // Drucker-Prager matched to Mohr-Coulomb in plane strain.
  const double deg = std::numbers::pi / 180.0;
  const double phi = r.in_range("friction_angle", 0.0, 90.0, true) * deg;
  const double psi = r.in_range("dilatancy_angle", 0.0, 90.0, true, 0.0) * deg;
  if (psi > phi) {
    r.fail_at(r.child("dilatancy_angle"), "expected a dilatancy angle <= the friction angle (" +
                                              Reader::fmt(phi / deg) + " degrees), got " +
                                              Reader::fmt(psi / deg));
  }
  const double c = r.in_range("cohesion", 0.0, 1e15, false, 0.0);
  const auto match = [](double angle) {
    const double t = std::tan(angle);
    return std::sqrt(9.0 + 12.0 * t * t);
  };
  DruckerPrager dp{
      rho, E, nu, std::tan(phi) / match(phi), std::tan(psi) / match(psi), 3.0 * c / match(phi),
      0.0};
  if (dp.alpha <= 0.0 && !r.has("tension_cutoff")) {
    r.fail_at(r.child("friction_angle"),
              "a friction angle of 0 needs an explicit tension_cutoff (the cone has no apex)");
  }
  const double apex = dp.alpha > 0.0 ? dp.k / (3.0 * dp.alpha) : 1e300;
  dp.tension_cutoff = r.in_range("tension_cutoff", 0.0, apex, false, dp.alpha > 0.0 ? apex : 0.0);
  return dp;
}

BodySpec read_body(Reader& r, int index, const Scene& scene,
                   const std::map<std::string, int>& material_index) {
  const int dim = scene.dimension;
  BodySpec body;
  body.name = r.string("name", "body" + std::to_string(index));
  const std::string material = r.string("material");
  const auto it = material_index.find(material);
  if (it == material_index.end()) {
    r.fail_at(r.child("material"), "no material named \"" + material + "\" in /materials");
  }
  body.material = it->second;
  body.particles_per_cell = r.integer("particles_per_cell", 1, 8, body.particles_per_cell);
  const Eigen::VectorXd zero = Eigen::VectorXd::Zero(dim);
  body.velocity = r.vector("velocity", dim, zero);
  body.body_force = r.vector("body_force", dim, zero);
  if (r.has("velocity_sine")) {
    Reader sine = r.object("velocity_sine");
    BodySpec::SineVelocity field;
    field.amplitude = sine.vector("amplitude", dim);
    field.wavenumber = sine.number("wavenumber");
    field.axis = sine.integer("axis", 0, dim - 1, 0);
    field.origin = sine.number("origin", 0.0);
    sine.finish();
    body.velocity_sine = field;
  }

  Reader shape = r.object("shape");
  const std::vector<std::string> types = dim == 1 ? std::vector<std::string>{"box", "segment"}
                                         : dim == 2
                                             ? std::vector<std::string>{"box", "disk"}
                                             : std::vector<std::string>{"box", "sphere", "mesh"};
  const std::string type = shape.choice("type", types);
  Eigen::VectorXd lo, hi;
  if (type == "box" || type == "segment") {
    body.shape = BodySpec::Shape::box;
    body.min = shape.vector("min", dim);
    body.max = shape.vector("max", dim);
    for (int d = 0; d < dim; ++d) {
      if (!(body.min[d] < body.max[d])) {
        shape.fail_at(shape.child("max") + "/" + std::to_string(d),
                      "must be greater than min (" + Reader::fmt(body.min[d]) + "), got " +
                          Reader::fmt(body.max[d]));
      }
    }
    lo = body.min;
    hi = body.max;
    body.own_lattice = shape.choice("lattice", {"grid", "body"}, "grid") == "body";
    if (shape.has("rotation")) {
      if (dim == 1) shape.fail_at(shape.child("rotation"), "a 1D body cannot be rotated");
      Eigen::Vector3d angles = Eigen::Vector3d::Zero();
      if (dim == 2) {
        angles[2] = shape.number("rotation");
      } else {
        angles = shape.vector("rotation", 3);
      }
      body.rotation = mpmgeom::rotation_from_degrees(angles);
      body.own_lattice = true;
      // The rotated corners bound the body.
      const Eigen::VectorXd centre = 0.5 * (body.min + body.max);
      const Eigen::VectorXd half = 0.5 * (body.max - body.min);
      lo = hi = centre;
      for (int corner = 0; corner < (1 << dim); ++corner) {
        Eigen::Vector3d offset = Eigen::Vector3d::Zero();
        for (int d = 0; d < dim; ++d) offset[d] = (corner >> d & 1) ? half[d] : -half[d];
        const Eigen::VectorXd x = centre + (body.rotation * offset).head(dim);
        lo = lo.cwiseMin(x);
        hi = hi.cwiseMax(x);
      }
    }
  } else if (type == "mesh") {
    // A closed surface (a source volume from CAD or a terrain tool) filled on the grid's
    // sub-cell lattice, or ("lattice": "body") on the same lattice in the file's own frame
    // (anchored at its origin, along its axes, after "scale"), carried by the placement's
    // rotation and translation: turning and moving the scene then turns and moves the particles
    // with the source instead of seeding it afresh against the grid.
    body.shape = BodySpec::Shape::mesh;
    const mpmgeom::ImportOptions import = read_placement(shape);
    const bool own_lattice = shape.choice("lattice", {"grid", "body"}, "grid") == "body";
    const std::filesystem::path file = scene_relative(scene, shape.string("file"));
    try {
      mpmgeom::RepairOptions repair;
      repair.require_closed = true;
      mpmgeom::ImportOptions frame = import;
      if (own_lattice) {
        frame.rotation_deg.setZero();
        frame.translation.setZero();
      }
      const mpmgeom::TriangleMesh imported = mpmgeom::load_mesh(file, frame);
      mpmgeom::check_extent(imported, file.string(),
                            (scene.box_max - scene.box_min).head(dim).norm());
      const mpmgeom::TriangleMesh mesh =
          mpmgeom::validate_and_repair(imported, file.string(), repair, nullptr);
      const Eigen::Vector3d origin =
          own_lattice ? Eigen::Vector3d::Zero() : Eigen::Vector3d(scene.box_min.head<3>());
      body.points =
          mpmgeom::fill_closed_surface(mesh, origin, scene.spacing, body.particles_per_cell);
      if (own_lattice) {
        const Eigen::Matrix3d R = mpmgeom::rotation_from_degrees(import.rotation_deg);
        body.points =
            ((body.points * R.transpose()).rowwise() + import.translation.transpose()).eval();
      }
    } catch (const std::exception& e) {
      shape.fail_at(shape.child("file"), e.what());
    }
    if (body.points.rows() == 0) {
      shape.fail_at(shape.child("file"), file.string() +
                                             " encloses no particle position at "
                                             "spacing " +
                                             Reader::fmt(scene.spacing) +
                                             " (too thin for the grid?)");
    }
    lo = body.points.colwise().minCoeff().transpose();
    hi = body.points.colwise().maxCoeff().transpose();
  } else {
    body.shape = BodySpec::Shape::sphere;
    body.center = shape.vector("center", dim);
    body.radius = shape.positive("radius");
    lo = body.center.array() - body.radius;
    hi = body.center.array() + body.radius;
  }
  shape.finish();
  for (int d = 0; d < dim; ++d) {
    if (lo[d] < scene.box_min[d] || hi[d] > scene.box_max[d]) {
      shape.fail("body extends outside the grid box /grid (axis " + std::to_string(d) + ": [" +
                 Reader::fmt(lo[d]) + ", " + Reader::fmt(hi[d]) + "] not inside [" +
                 Reader::fmt(scene.box_min[d]) + ", " + Reader::fmt(scene.box_max[d]) + "])");
    }
  }
  return body;
}

/// "condition" (and "mu" for friction): of a wall, or of a part of a dual-grid wall.
WallCondition read_condition(Reader& r) {
  const std::string condition = r.choice("condition", {"sticky", "slip", "friction"});
  if (condition == "friction") {
    const double mu = r.number("mu");
    if (!(mu >= 0.0)) r.fail_at(r.child("mu"), "expected a friction coefficient >= 0");
    return Friction{mu};
  }
  if (r.has("mu")) r.fail_at(r.child("mu"), "only used with \"condition\": \"friction\"");
  if (condition == "sticky") return Sticky{};
  return Slip{};
}

/// touch: whether the wall decides contact by touch (dual-grid Blending and Enhanced walls);
/// box and sdf walls act on every node near them, as standard MPM does.
WallContact read_contact(Reader& r, bool touch) {
  WallContact contact;
  contact.condition = read_condition(r);
  contact.separable = r.boolean("separable", contact.separable);
  if (r.has("touch_tolerance")) {
    if (!touch) {
      r.fail_at(r.child("touch_tolerance"),
                "only used by dual-grid walls (method mortar, one-way or enhanced)");
    }
    contact.touch_tolerance = r.in_range("touch_tolerance", 0.0, 1e6, false);
    if (!contact.separable) {
      r.fail_at(r.child("touch_tolerance"), "only used with \"separable\": true");
    }
  }
  return contact;
}

BoxWall read_wall(Reader& r, int dim) {
  static const char* const kFaces[] = {"xmin", "xmax", "ymin", "ymax", "zmin", "zmax"};
  std::vector<std::string> faces(kFaces, kFaces + 2 * dim);
  BoxWall wall;
  wall.name = r.choice("face", faces);
  for (int f = 0; f < 2 * dim; ++f) {
    if (faces[f] == wall.name) {
      wall.axis = f / 2;
      wall.side = f % 2 == 0 ? -1 : 1;
    }
  }
  wall.contact = read_contact(r, false);
  return wall;
}

/// A dual-grid wall: the surface it follows, its layer and coupling, built here so that any
/// problem is reported against the scene key.
DualWallSpec read_dual_wall(Reader& r, int index, const Scene& scene) {
  const int dim = scene.dimension;
  DualWallSpec wall;
  wall.name = r.string("name", "wall" + std::to_string(index));
  const std::string method = r.choice("method", {"mortar", "one-way", "enhanced", "sdf"}, "mortar");
  wall.method = method == "one-way"    ? CouplingMethod::one_way
                : method == "enhanced" ? CouplingMethod::enhanced
                : method == "sdf"      ? CouplingMethod::sdf
                                       : CouplingMethod::mortar;
  wall.contact = read_contact(r, wall.method != CouplingMethod::sdf);
  const bool blending =
      wall.method == CouplingMethod::mortar || wall.method == CouplingMethod::one_way;
  if (r.has("multiplier_radius")) {
    if (!blending) {
      r.fail_at(r.child("multiplier_radius"),
                "only used by Blending walls (method mortar or one-way)");
    }
    wall.multiplier_radius = r.in_range("multiplier_radius", 0.0, 8.0, false);
  }
  wall.corner_facets = blending;
  if (r.has("corners")) {
    if (!blending) {
      r.fail_at(r.child("corners"), "only used by Blending walls (method mortar or one-way)");
    }
    wall.corner_facets = r.choice("corners", {"normal", "facets"}) == "facets";
  }
  const mpmgeom::GridSpec grid =
      standard_grid_spec(dim, scene.box_min, scene.box_max, scene.spacing, scene.shape);

  Reader surface = r.object("surface");
  const std::vector<std::string> types = dim == 1   ? std::vector<std::string>{"point"}
                                         : dim == 2 ? std::vector<std::string>{"polyline"}
                                                    : std::vector<std::string>{"mesh", "package"};
  const std::string type = surface.choice("type", types);
  auto package = std::make_shared<BoundaryPackage>();
  try {
    if (type == "package") {
      const std::string file = surface.string("file");
      *package = load_boundary_package(scene_relative(scene, file));
      const mpmgeom::GridSpec& g = package->grid;
      if (g.dimension != grid.dimension || g.kernel != grid.kernel || g.spacing != grid.spacing ||
          g.nodes != grid.nodes || (g.origin - grid.origin).norm() > 1e-9 * grid.spacing) {
        surface.fail_at(surface.child("file"),
                        "boundary package '" + file + "' was made for another grid (spacing " +
                            Reader::fmt(g.spacing) + ", kernel " +
                            (g.kernel == grid.kernel ? "same" : "different") +
                            "); run mpm prep with this scene's grid box, spacing and shape");
      }
    } else {
      mpmgeom::LayerOptions layer;
      layer.thickness = r.positive("thickness", scene.spacing);
      layer.layers = r.integer("layers", 1, 16, 1);
      package->grid = grid;
      if (type == "point") {
        const double position = surface.number("position");
        const int side = surface.integer("side", -1, 1, 1);
        if (side == 0) surface.fail_at(surface.child("side"), "expected +1 or -1");
        package->layer = mpmgeom::layer_1d(position, side, layer, wall.name, &package->report);
      } else if (type == "polyline") {
        const nlohmann::json& points = surface.required("points");
        if (!points.is_array() || points.size() < 2) {
          surface.fail_at(surface.child("points"), "expected an array of at least two [x, y]");
        }
        Eigen::MatrixX2d polyline(points.size(), 2);
        for (std::size_t i = 0; i < points.size(); ++i) {
          const auto& pt = points[i];
          if (!pt.is_array() || pt.size() != 2 || !pt[0].is_number() || !pt[1].is_number()) {
            surface.fail_at(surface.child("points") + "/" + std::to_string(i),
                            "expected [x, y], got " + describe(pt));
          }
          polyline.row(static_cast<Eigen::Index>(i)) << pt[0].get<double>(), pt[1].get<double>();
        }
        const bool closed = surface.boolean("closed", false);
        if (surface.boolean("remesh", true)) {
          // Segments of at most h, as the 3D reader remeshes meshes to h: a straight wall written
          // as two points would otherwise be one boundary cell carrying everything on its ends.
          std::vector<Eigen::RowVector2d> cut;
          const Eigen::Index n = polyline.rows();
          const Eigen::Index segments = closed ? n : n - 1;
          for (Eigen::Index i = 0; i < segments; ++i) {
            const Eigen::RowVector2d a = polyline.row(i), b = polyline.row((i + 1) % n);
            const int pieces =
                std::max(1, static_cast<int>(std::ceil((b - a).norm() / scene.spacing - 1e-9)));
            for (int k = 0; k < pieces; ++k) cut.push_back(a + (b - a) * (double(k) / pieces));
          }
          if (!closed) cut.push_back(polyline.row(n - 1));
          polyline.resize(static_cast<Eigen::Index>(cut.size()), 2);
          for (std::size_t i = 0; i < cut.size(); ++i) {
            polyline.row(static_cast<Eigen::Index>(i)) = cut[i];
          }
        }
        package->layer =
            mpmgeom::extrude_layer_2d(polyline, closed, layer, wall.name, &package->report);
      } else {
        PrepOptions prep;
        prep.layer = layer;
        prep.import = read_placement(surface);
        prep.remesh = surface.boolean("remesh", true);
        prep.repair.require_closed = surface.boolean("closed", false);
        const std::filesystem::path mesh_file = scene_relative(scene, surface.string("file"));
        // "cache": a package file reused while it matches the mesh bytes, the options and the
        // grid (its digest), else rebuilt here and written there for the next run.
        std::filesystem::path cache;
        if (surface.has("cache")) cache = scene_relative(scene, surface.string("cache"));
        bool reused = false;
        std::error_code ec;
        if (!cache.empty() && std::filesystem::is_regular_file(cache, ec)) {
          try {
            BoundaryPackage cached = load_boundary_package(cache);
            if (cached.source_digest == boundary_digest(mesh_file, prep, grid)) {
              *package = std::move(cached);
              reused = true;
            }
          } catch (const std::exception&) {
            // An unreadable or foreign cache file is rebuilt below, not an error.
          }
        }
        if (!reused) {
          *package = prepare_boundary(mesh_file, prep, grid);
          if (!cache.empty()) {
            std::filesystem::path xmf = cache;
            xmf.replace_extension(".xmf");
            if (cache.has_parent_path()) std::filesystem::create_directories(cache.parent_path());
            save_boundary_package(*package, cache, xmf);
          }
        }
      }
      if (type != "mesh") {
        package->interface_coupling =
            mpmgeom::couple(package->layer, grid, mpmgeom::CouplingSurface::interface);
        package->wall_coupling =
            mpmgeom::couple(package->layer, grid, mpmgeom::CouplingSurface::wall);
        package->cell_flags = mpmgeom::layer_cell_flags(package->layer, grid);
      }
    }
  } catch (const SceneError&) {
    throw;
  } catch (const std::exception& e) {
    surface.fail(e.what());
  }
  surface.finish();
  wall.package = std::move(package);

  // "parts": {"barrier": {"condition": ..., "mu": ...}}: another condition on a named part.
  const std::vector<std::string>& names = wall.package->layer.part_names;
  wall.part_condition.assign(std::max<std::size_t>(names.size(), 1), wall.contact.condition);
  if (r.has("parts")) {
    if (wall.method == CouplingMethod::sdf) {
      r.fail_at(r.child("parts"), "sdf walls take one condition (no parts)");
    }
    Reader parts = r.object("parts");
    std::string known;
    for (const auto& n : names) known += (known.empty() ? "" : ", ") + n;
    for (const auto& item : r.required("parts").items()) {
      const auto at = std::find(names.begin(), names.end(), item.key());
      if (at == names.end()) {
        parts.fail_at(parts.child(item.key()), "the surface has no part named \"" + item.key() +
                                                   "\" (its parts: " + known + ")");
      }
      Reader part = parts.object(item.key());
      wall.part_condition[static_cast<std::size_t>(at - names.begin())] = read_condition(part);
      part.finish();
    }
    parts.finish();
  }
  return wall;
}

}  // namespace

double max_wave_speed(const Scene& scene) {
  double c = 0.0;
  for (const auto& m : scene.materials) {
    switch (scene.dimension) {
      case 1:
        c = std::max(c, wave_speed<1>(m.model));
        break;
      case 2:
        c = std::max(c, wave_speed<2>(m.model));
        break;
      default:
        c = std::max(c, wave_speed<3>(m.model));
    }
  }
  return c;
}

Scene parse_scene(const json& doc, const std::filesystem::path& origin) {
  const std::string file = origin.string();
  Reader root(doc, "", file);
  Scene scene;
  scene.file = origin;
  scene.name = root.string("name", origin.stem().string());
  const int dim = scene.dimension = root.integer("dimension", 1, 3);

  {
    Reader grid = root.object("grid");
    scene.box_min = grid.vector("min", dim);
    scene.box_max = grid.vector("max", dim);
    scene.spacing = grid.positive("spacing");
    double nodes = 1.0;
    for (int d = 0; d < dim; ++d) {
      const double cells = (scene.box_max[d] - scene.box_min[d]) / scene.spacing;
      if (!(cells >= 1.0)) {
        grid.fail_at(grid.child("max") + "/" + std::to_string(d),
                     "the box must be at least one cell (spacing) wide on every axis");
      }
      // Walls sit on the box faces, which must be grid lines.
      if (std::abs(cells - std::round(cells)) > 1e-6 * cells) {
        grid.fail_at(grid.child("spacing"), "box extent " +
                                                Reader::fmt(scene.box_max[d] - scene.box_min[d]) +
                                                " on axis " + std::to_string(d) +
                                                " is not a whole number of cells of spacing " +
                                                Reader::fmt(scene.spacing));
      }
      nodes *= std::round(cells) + 5.0;  // plus the padding the solver adds
    }
    if (nodes > 4e8) {
      grid.fail_at(grid.child("spacing"), "the grid would have " + Reader::fmt(nodes) +
                                              " nodes (limit 4e8); use a larger spacing");
    }
    const std::string storage = grid.choice("storage", {"auto", "dense", "sparse"}, "auto");
    scene.grid_storage = storage == "dense"    ? GridStorage::dense
                         : storage == "sparse" ? GridStorage::sparse
                                               : GridStorage::automatic;
    grid.finish();
  }

  const std::string shape =
      root.choice("shape_function", {"linear", "gimp", "bspline2"}, "bspline2");
  scene.shape = shape == "linear" ? ShapeKind::linear
                : shape == "gimp" ? ShapeKind::gimp
                                  : ShapeKind::bspline2;

  if (root.has("scheme")) {
    Reader scheme = root.object("scheme");
    const std::string update = scheme.choice("update", {"usl", "musl", "mls"}, "musl");
    scene.update = update == "usl"   ? UpdateScheme::usl
                   : update == "mls" ? UpdateScheme::mls
                                     : UpdateScheme::musl;
    const std::string transfer = scheme.choice("transfer", {"apic", "flip", "pic"}, "apic");
    scene.transfer = transfer == "apic" ? Transfer::apic : Transfer::flip;
    if (transfer == "flip") {
      scene.flip_blend = scheme.in_range("flip_blend", 0.0, 1.0, false, 0.99);
    } else {
      scene.flip_blend = 0.0;
      if (scheme.has("flip_blend")) {
        scheme.fail_at(scheme.child("flip_blend"), "only used with \"transfer\": \"flip\"");
      }
    }
    if (scene.update == UpdateScheme::mls &&
        (scene.transfer != Transfer::apic || scene.shape != ShapeKind::bspline2)) {
      // The MLS force and gradient take C_p = B_p D^-1, with D constant only for the B-spline.
      scheme.fail_at(scheme.child("update"),
                     "\"mls\" needs \"transfer\": \"apic\" and \"shape_function\": \"bspline2\"");
    }
    // The keys left out keep Scene's defaults (scene.hpp says what each means).
    scene.mass_threshold = scheme.in_range("mass_threshold", 0.0, 0.5, false, scene.mass_threshold);
    scene.coupling_mass_threshold =
        scheme.in_range("coupling_mass_threshold", 0.0, 0.5, false, scene.coupling_mass_threshold);
    scene.coupling_tolerance =
        scheme.in_range("coupling_tolerance", 1e-13, 1e-3, false, scene.coupling_tolerance);
    scene.dependence_tolerance =
        scheme.in_range("dependence_tolerance", 0.0, 1.0, false, scene.dependence_tolerance);
    scene.drop_covered_enhancement =
        scheme.boolean("drop_covered_enhancement", scene.drop_covered_enhancement);
    scheme.finish();
  }

  scene.gravity = root.vector("gravity", dim, Eigen::VectorXd::Zero(dim));

  std::map<std::string, int> material_index;
  for (auto& m : root.objects("materials", false)) {
    MaterialSpec spec;
    spec.name = m.string("name");
    if (material_index.count(spec.name) != 0) {
      m.fail_at(m.child("name"), "duplicate material name \"" + spec.name + "\"");
    }
    spec.model = read_material(m, dim);
    m.finish();
    material_index[spec.name] = static_cast<int>(scene.materials.size());
    scene.materials.push_back(std::move(spec));
  }

  {
    auto bodies = root.objects("bodies", false);
    for (std::size_t i = 0; i < bodies.size(); ++i) {
      scene.bodies.push_back(read_body(bodies[i], static_cast<int>(i), scene, material_index));
      bodies[i].finish();
    }
  }

  if (root.has("walls")) {
    std::set<std::string> faces;
    auto walls = root.objects("walls", true);
    for (std::size_t i = 0; i < walls.size(); ++i) {
      Reader& w = walls[i];
      if (w.has("surface")) {
        scene.dual_walls.push_back(read_dual_wall(w, static_cast<int>(i), scene));
      } else {
        BoxWall wall = read_wall(w, dim);
        if (!faces.insert(wall.name).second) {
          w.fail_at(w.child("face"), "a second wall on face " + wall.name);
        }
        scene.walls.push_back(std::move(wall));
      }
      w.finish();
    }
  }

  {
    Reader time = root.object("time");
    scene.end_time = time.positive("end");
    scene.cfl = time.in_range("cfl", 1e-6, 1.0, false, scene.cfl);
    if (time.has("dt")) {
      scene.fixed_dt = time.positive("dt");
      // Explicit MPM is stable for dt <= h / c (CFL number 1) at best, and for viscous
      // materials dt <= rho h^2 / (2 D mu).
      const double limit =
          std::min(scene.spacing / max_wave_speed(scene), viscous_dt_limit(scene, scene.spacing));
      if (*scene.fixed_dt > limit) {
        time.fail_at(time.child("dt"),
                     "time step " + Reader::fmt(*scene.fixed_dt) +
                         " is above the stability limit h/c = " + Reader::fmt(limit) +
                         " (CFL number " + Reader::fmt(*scene.fixed_dt / limit) + " > 1)");
      }
    }
    time.finish();
  }

  scene.output_interval = scene.end_time / 50.0;
  if (root.has("output")) {
    Reader output = root.object("output");
    scene.output_interval = output.positive("interval", scene.output_interval);
    scene.history_interval = output.number("history_interval", scene.history_interval);
    if (scene.history_interval < 0.0) {
      output.fail_at(output.child("history_interval"), "expected a number >= 0 (0: every step)");
    }
    if (output.has("runout_depths")) {
      const json& depths = output.required("runout_depths");
      if (!depths.is_array() || depths.empty()) {
        output.fail_at(output.child("runout_depths"),
                       "expected a non-empty array of depths in metres, got " + describe(depths));
      }
      for (std::size_t i = 0; i < depths.size(); ++i) {
        const json& d = depths[i];
        if (!d.is_number() || !(d.get<double>() > 0.0) || !std::isfinite(d.get<double>())) {
          output.fail_at(output.child("runout_depths") + "/" + std::to_string(i),
                         "expected a positive depth in metres, got " + describe(d));
        }
        scene.runout_depths.push_back(d.get<double>());
      }
    }
    if (output.has("retaining_walls")) {
      const json& names = output.required("retaining_walls");
      if (!names.is_array()) {
        output.fail_at(output.child("retaining_walls"), "expected an array of wall names");
      }
      for (std::size_t i = 0; i < names.size(); ++i) {
        // A dual-grid wall, or one part of it as the force history names it (wall_part).
        std::optional<Scene::RetainingWall> found;
        for (std::size_t w = 0; w < scene.dual_walls.size() && names[i].is_string(); ++w) {
          const DualWallSpec& spec = scene.dual_walls[w];
          const std::string name = names[i].get<std::string>();
          const auto& parts = spec.package->layer.part_names;
          if (spec.name == name) found = Scene::RetainingWall{name, static_cast<int>(w), -1};
          for (std::size_t k = 0; k < parts.size(); ++k) {
            if (spec.name + "_" + parts[k] == name) {
              found = Scene::RetainingWall{name, static_cast<int>(w), static_cast<int>(k)};
            }
          }
        }
        if (!found) {
          output.fail_at(output.child("retaining_walls") + "/" + std::to_string(i),
                         "expected the name of a dual-grid wall in /walls (or wall_part), got " +
                             describe(names[i]));
        }
        scene.retaining_walls.push_back(*found);
      }
    }
    output.finish();
  }
  root.finish();
  return scene;
}

Scene load_scene(const std::filesystem::path& file, int resolution) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(file, ec)) {
    throw SceneError(file.string() + ": scene file does not exist or is not a file");
  }
  std::ifstream in(file);
  if (!in) throw SceneError(file.string() + ": cannot open the scene file");
  json doc;
  try {
    doc = json::parse(in);
  } catch (const json::exception& e) {
    // A syntax error ("[json.exception.parse_error.101] parse error at line 3, column 5: ...")
    // or a number too large for a double ("[json.exception.out_of_range.406] number overflow
    // parsing '1.0e6333...'", found by fuzz_scene: it escaped as an uncaught exception).
    std::string what = e.what();
    const auto tag = what.find("] ");
    throw SceneError(file.string() +
                     ": invalid JSON: " + (tag == std::string::npos ? what : what.substr(tag + 2)));
  }
  if (resolution < 1)
    throw SceneError(file.string() + ": resolution " + std::to_string(resolution) +
                     " is not a positive integer");
  if (resolution > 1) {
    // Only well-formed values are refined: parse_scene reports anything else as it stands.
    for (const char* key : {"/grid/spacing", "/time/dt"}) {
      const json::json_pointer at(key);
      if (doc.contains(at) && doc[at].is_number()) doc[at] = doc[at].get<double>() / resolution;
    }
    if (doc.is_object() && doc.contains("walls") && doc["walls"].is_array()) {
      for (json& wall : doc["walls"]) {
        if (!wall.is_object() || !wall.contains("surface") || !wall["surface"].is_object())
          continue;
        json& surface = wall["surface"];
        if (!surface.contains("cache") || !surface["cache"].is_string()) continue;
        std::filesystem::path cache = surface["cache"].get<std::string>();
        cache.replace_filename(cache.stem().string() + "_r" + std::to_string(resolution) +
                               cache.extension().string());
        surface["cache"] = cache.string();
      }
    }
  }
  Scene scene = parse_scene(doc, file);
  scene.resolution = resolution;
  return scene;
}

std::string_view to_string(ShapeKind kind) {
  switch (kind) {
    case ShapeKind::linear:
      return "linear";
    case ShapeKind::gimp:
      return "gimp";
    case ShapeKind::bspline2:
      break;
  }
  return "bspline2";
}

std::string_view model_name(const Material& m) {
  static constexpr std::string_view names[] = {"linear_elastic", "neo_hookean", "drucker_prager",
                                               "newtonian_fluid", "bingham"};
  static_assert(std::size(names) == std::variant_size_v<Material>);
  if (const auto* dp = std::get_if<DruckerPrager>(&m); dp != nullptr && dp->grain_diameter > 0.0) {
    return "mu_i";
  }
  return names[m.index()];
}

double viscous_dt_limit(const Scene& scene, double size) {
  double limit = std::numeric_limits<double>::infinity();
  for (const auto& m : scene.materials) {
    const double mu = max_viscosity(m.model);
    if (mu > 0.0) {
      limit = std::min(limit, density(m.model) * size * size / (2.0 * scene.dimension * mu));
    }
  }
  return limit;
}

}  // namespace mpm
