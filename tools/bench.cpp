// `mpm bench`: run time against error, and numerical-stability stress.
//
// accuracy: every series of data/bench/accuracy.json (a verification case with the parameters to
//   sweep, its resolutions and wall methods) is run per method and refinement factor; the row is
//   the wall time of the runs and the largest error of the checks the series measures. CSV, and
//   the Pareto plot (error against time, log-log) by scripts/bench_plot.py.
// stability: four parts, each run counted as failed when it faults (NaN/inf, an inverted
//   element, a particle leaving the grid), a particle centre goes into the wall deeper than the
//   tolerance, or the energy grows by more than 1% of its scale; a failing run's scene is written
//   out so that `mpm run` reruns it alone.
//   throws:   random wall placements (offset, orientation; 2D and 3D), blocks thrown at the wall
//   long:     10^5 steps of a block resting on a frictional incline: energy drift, creep
//   cfl:      the largest stable CFL number per wall method, shape function and transfer
//   crossing: a disk rolling on an incline, its particles crossing Phi (layer <-> bulk) each step

#include <unistd.h>
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <limits>
#include <map>
#include <numbers>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "cases.hpp"
#include "commands.hpp"
#include "mpm/run.hpp"
#include "process.hpp"
#include "support/temp_directory.hpp"

namespace mpm::tools {
namespace {

using nlohmann::json;
constexpr double kGravity = 9.81;
constexpr double kPi = std::numbers::pi;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

/// A bad configuration: reported as one line naming the file and key, exit 2.
struct ConfigError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

template <class T>
T config_value(const json& j, const std::string& key, const std::string& where) {
  if (!j.contains(key)) throw ConfigError(where + "/" + key + ": missing");
  try {
    return j.at(key).get<T>();
  } catch (const json::exception&) {
    throw ConfigError(where + "/" + key + ": wrong type");
  }
}

/// A CSV field in double quotes, its own double quotes doubled (RFC 4180): fault messages quote
/// material and body names.
std::string quoted(const std::string& text) {
  std::string out = "\"";
  for (const char c : text) {
    out += c;
    if (c == '"') out += '"';
  }
  return out + "\"";
}

bool selected(const std::vector<std::string>& filter, const std::string& name) {
  return filter.empty() || std::find(filter.begin(), filter.end(), name) != filter.end();
}

/// Draws the plot with scripts/bench_plot.py; false (and a message) when it cannot.
bool plot(const BenchArgs& args, const std::filesystem::path& csv) {
  const std::filesystem::path script = args.scripts_dir / "bench_plot.py";
  // Debian's own interpreter, which the python3-matplotlib package serves (another python3 may
  // come first on PATH).
  const std::string python =
      std::filesystem::exists("/usr/bin/python3") ? "/usr/bin/python3" : "python3";
  const ProcessResult run = run_process(
      {python, script.string(), args.kind, csv.string(), args.plot_file.string()}, false);
  if (!run.error.empty() || run.exit_code != 0) {
    std::cerr << "mpm bench: --plot " << args.plot_file.string() << ": " << script.string()
              << " failed (it needs python3-matplotlib: scripts/bench.sh installs it)\n";
    return false;
  }
  return true;
}

// ---------------------------------------------------------------------------------------------
// Accuracy: run time against error.

struct AccuracyRow {
  std::string series, case_name, method;
  int resolution = 1;
  double spacing = 0.0, seconds = 0.0, error = 0.0;
  int checks = 0;
  std::string fault;
};

int accuracy(const BenchArgs& args, const json& config) {
  const std::string file = args.config.string();
  if (!config.contains("series") || !config["series"].is_array()) {
    throw ConfigError(file + ": /series: missing or not an array");
  }
  // Every --case names a series of the file (checked before anything runs).
  std::set<std::string> known;
  for (const json& entry : config["series"]) {
    if (entry.contains("measures") && entry["measures"].is_object()) {
      for (const auto& [series, substring] : entry["measures"].items()) known.insert(series);
    }
  }
  for (const std::string& name : args.cases) {
    if (known.count(name) == 0) throw ConfigError(file + ": no series \"" + name + "\"");
  }
  std::vector<AccuracyRow> rows;
  for (std::size_t e = 0; e < config["series"].size(); ++e) {
    const json& entry = config["series"][e];
    const std::string where = file + ": /series/" + std::to_string(e);
    const auto case_name = config_value<std::string>(entry, "case", where);
    const auto params = config_value<json>(entry, "params", where);
    const auto measures =
        config_value<std::map<std::string, std::string>>(entry, "measures", where);
    auto resolutions = config_value<std::vector<int>>(entry, "resolutions", where);
    const auto methods = config_value<std::vector<std::string>>(entry, "methods", where);
    if (checkers().count(case_name) == 0) throw ConfigError(where + "/case: no case " + case_name);
    if (resolutions.empty()) throw ConfigError(where + "/resolutions: empty");
    for (const int k : resolutions) {
      if (k < 1 || k > 64) throw ConfigError(where + "/resolutions: " + std::to_string(k));
    }
    // A sweep key runs the case once per value (e.g. wall offsets); the error is the largest.
    std::string sweep_key;
    std::vector<json> sweep_values{json()};
    if (entry.contains("sweep")) {
      const auto sweep =
          config_value<std::map<std::string, std::vector<double>>>(entry, "sweep", where);
      if (sweep.size() != 1 || sweep.begin()->second.empty()) {
        throw ConfigError(where + "/sweep: one key with a non-empty list of values");
      }
      sweep_key = sweep.begin()->first;
      sweep_values.assign(sweep.begin()->second.begin(), sweep.begin()->second.end());
    }
    bool wanted = false;
    for (const auto& [series, substring] : measures)
      wanted = wanted || selected(args.cases, series);
    if (!wanted) continue;
    if (args.smoke) {
      if (!entry.value("smoke", false)) continue;
      resolutions.resize(1);
      if (sweep_values.size() > 1) sweep_values.resize(2);
    }
    for (const std::string& method : methods) {
      if (!selected(args.methods, method)) continue;
      for (const int k : resolutions) {
        std::vector<Check> checks;
        const auto start = std::chrono::steady_clock::now();
        for (const json& value : sweep_values) {
          json p = params;
          if (!sweep_key.empty()) p[sweep_key] = value;
          try {
            for (Check& c : checkers().at(case_name)(p, method, k)) checks.push_back(c);
          } catch (const std::exception& ex) {
            throw ConfigError(where + ": " + ex.what());
          }
        }
        const double seconds =
            std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
        for (const auto& [series, substring] : measures) {
          if (!selected(args.cases, series)) continue;
          AccuracyRow row;
          row.series = series;
          row.case_name = case_name;
          row.method = method;
          row.resolution = k;
          row.spacing = params.value("spacing", 0.0) / k;
          row.seconds = seconds;
          for (const Check& c : checks) {
            if (c.measure.find(substring) == std::string::npos) continue;
            ++row.checks;
            if (!c.note.empty() && row.fault.empty()) row.fault = c.note;
            if (!std::isfinite(c.value) && row.fault.empty()) row.fault = "non-finite error";
            row.error = std::max(row.error, c.value);
          }
          if (row.checks == 0) {
            throw ConfigError(where + "/measures/" + series + ": no check of " + case_name +
                              " measures \"" + substring + "\"");
          }
          if (!row.fault.empty()) row.error = kNaN;
          std::printf("%-24s %-9s %2d  h %-9.4g %9.3f s  error %10.3e%s%s\n", row.series.c_str(),
                      method.c_str(), k, row.spacing, seconds, row.error,
                      row.fault.empty() ? "" : "  FAULT ", row.fault.c_str());
          std::fflush(stdout);
          rows.push_back(row);
        }
      }
    }
  }
  std::filesystem::path csv = args.csv_file;
  if (csv.empty() && !args.plot_file.empty()) {
    csv = mpm::test::temporary_directory("the accuracy table behind the plot") /
          ("mpm_bench_" + std::to_string(::getpid()) + ".csv");
  }
  if (!csv.empty()) {
    std::ofstream out(csv);
    out << "series,case,method,resolution,spacing,seconds,error,checks,fault\n";
    out.precision(9);
    for (const AccuracyRow& r : rows) {
      out << r.series << ',' << r.case_name << ',' << r.method << ',' << r.resolution << ','
          << r.spacing << ',' << r.seconds << ',' << r.error << ',' << r.checks << ','
          << quoted(r.fault) << '\n';
    }
    if (!out) {
      std::cerr << "mpm bench: cannot write " << csv.string() << "\n";
      return kExitIo;
    }
  }
  if (!args.plot_file.empty() && !plot(args, csv)) return kExitIo;
  if (args.csv_file.empty() && !csv.empty()) std::filesystem::remove(csv);
  std::size_t faults = 0;
  for (const AccuracyRow& r : rows) faults += r.fault.empty() ? 0 : 1;
  std::printf("%zu rows, %zu with a numerical fault\n", rows.size(), faults);
  return faults == 0 ? 0 : 1;
}

// ---------------------------------------------------------------------------------------------
// Stability.

/// A flat wall for the stress runs: a point on it, its unit normal into the material and its
/// in-plane axes (3D: two), over [-extent, extent] along each.
struct Plane {
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  Eigen::Vector3d normal = Eigen::Vector3d::UnitY();
  Eigen::Vector3d s = Eigen::Vector3d::UnitX(), t = Eigen::Vector3d::UnitZ();
  double extent = 1.0;
};

/// The criteria every stress run is held to.
struct Limits {
  double penetration = 0.25;  ///< particle centre behind the wall, in h
  double energy = 0.01;       ///< growth over the energy scale
};

/// What one stress run did.
struct Outcome {
  std::string part{}, method{}, kernel{};  ///< kernel: shape function/transfer
  std::string detail{}, fault{}, scene_file{};
  int dimension = 2;
  int id = 0;
  double cfl = 0.0;
  std::int64_t steps = 0;
  double seconds = 0.0;
  double penetration = 0.0;    ///< deepest particle centre behind the wall / h
  double closest = kNaN;       ///< smallest distance of a particle centre from the wall / h
  double energy_growth = 0.0;  ///< (max E(t) - E(0)) / energy scale
  double energy_drift = 0.0;   ///< (E(end) - E(0)) / energy scale
  double creep = kNaN;         ///< long: |centre of mass travel| / h
  double crossings = kNaN;     ///< crossing: particles changing owner per step
  double error = kNaN;         ///< crossing: |d/d_exact - 1|
  std::vector<std::string> reasons{};
  [[nodiscard]] bool failed() const { return !reasons.empty(); }
};

/// Calls f(position, mass) for every particle of `sim`, read in place (a ParticleFrame would copy
/// stresses and velocities every step only for this).
template <class F>
void for_each_particle(const Simulation& sim, F&& f) {
  auto each = [&](const auto& solver) {
    const auto& P = solver.particles;
    for (std::size_t i = 0; i < P.size(); ++i) f(pad3(P.position[i]), P.mass[i]);
  };
  if (const auto* s2 = dynamic_cast<const Solver<2>*>(&sim)) {
    each(*s2);
  } else if (const auto* s3 = dynamic_cast<const Solver<3>*>(&sim)) {
    each(*s3);
  } else {
    each(dynamic_cast<const Solver<1>&>(sim));
  }
}

/// Watches a run: the deepest particle centre behind the plane (over the plane's extent less
/// `margin`) and the energy relative to the plane's origin, E = kinetic + strain - sum m g.(x - o).
struct Monitor {
  Plane plane;
  Eigen::Vector3d gravity = Eigen::Vector3d::Zero();
  double h = 1.0, margin = 0.0, mass = 0.0, scale = 0.0;
  double e0 = 0.0, e_max = -std::numeric_limits<double>::infinity(), e_end = 0.0;
  double deepest = 0.0;
  double closest = std::numeric_limits<double>::infinity();
  Eigen::Vector3d com0 = Eigen::Vector3d::Zero(), com = Eigen::Vector3d::Zero();

  double energy(const Simulation& sim) const {
    return sim.energies().total() + mass * gravity.dot(plane.origin);
  }
  void watch(const Simulation& sim, bool first) {
    double m = 0.0;
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    const double lim = plane.extent - margin;
    for_each_particle(sim, [&](const Eigen::Vector3d& x, double mp) {
      m += mp;
      c += mp * x;
      const Eigen::Vector3d r = x - plane.origin;
      if (std::abs(r.dot(plane.s)) > lim || std::abs(r.dot(plane.t)) > lim) return;
      deepest = std::max(deepest, -r.dot(plane.normal) / h);
      closest = std::min(closest, r.dot(plane.normal) / h);
    });
    com = c / m;
    if (first) {
      mass = m;
      com0 = com;
      e0 = energy(sim);
    }
    e_end = energy(sim);
    e_max = std::max(e_max, e_end);
  }
  void judge(Outcome& o, const Limits& limits) const {
    o.penetration = deepest;
    o.closest = closest;
    o.energy_growth = (e_max - e0) / scale;
    o.energy_drift = (e_end - e0) / scale;
    if (!o.fault.empty()) o.reasons.push_back("fault");
    if (!(o.penetration <= limits.penetration)) o.reasons.push_back("penetration");
    if (!(o.energy_growth <= limits.energy)) o.reasons.push_back("energy");
  }
};

/// A monitor of `plane` for particles at spacing h (the plane's last h left out), energy scale
/// `scale`.
Monitor watch(const Plane& plane, const Eigen::Vector3d& gravity, double h, double scale) {
  return Monitor{.plane = plane, .gravity = gravity, .h = h, .margin = h, .scale = scale};
}

/// An outcome to be filled by a run of `part`.
Outcome outcome(const std::string& part, const std::string& method, const std::string& kernel,
                double cfl, int dimension = 2) {
  return Outcome{
      .part = part, .method = method, .kernel = kernel, .dimension = dimension, .cfl = cfl};
}

/// A scene with a flat wall `plane` (dual-grid, sdf, or for "grid" the box face below the
/// material: the plane must then be y = 0 in 2D, z = 0 in 3D), a grid box spanning the plane's
/// extent and `height` above it, and `body`; `kernel` is "shape function/transfer" (MUSL).
json plane_doc(int dim, const Plane& plane, double height, const std::string& method, double h,
               const std::string& kernel, double mu, const json& body, const json& material,
               const Eigen::Vector3d& gravity, double end, double cfl,
               const std::filesystem::path& mesh_file) {
  Eigen::Vector3d lo = plane.origin, hi = plane.origin;
  for (const double a : {-1.0, 1.0}) {
    for (const double b : {-1.0, 1.0}) {
      for (const double c : {0.0, height}) {
        const Eigen::Vector3d x =
            plane.origin + plane.extent * (a * plane.s + b * plane.t) + c * plane.normal;
        lo = lo.cwiseMin(x);
        hi = hi.cwiseMax(x);
      }
    }
  }
  json mn = json::array(), mx = json::array(), g = json::array();
  for (int d = 0; d < dim; ++d) {
    mn.push_back(h * (std::floor(lo[d] / h) - 3));
    mx.push_back(h * (std::ceil(hi[d] / h) + 3));
    g.push_back(gravity[d]);
  }
  json doc = {{"dimension", dim},
              {"grid", {{"min", mn}, {"max", mx}, {"spacing", h}}},
              {"shape_function", kernel.substr(0, kernel.find('/'))},
              {"scheme", {{"update", "musl"}, {"transfer", kernel.substr(kernel.find('/') + 1)}}},
              {"gravity", g},
              {"materials", json::array({material})},
              {"bodies", json::array({body})},
              {"time", {{"end", end}, {"cfl", cfl}}}};
  json wall = contact(mu, true);
  if (method == "grid") {
    doc["grid"]["min"][dim - 1] = 0.0;
    wall["face"] = dim == 2 ? "ymin" : "zmin";
  } else if (dim == 2) {
    wall["name"] = "wall";
    wall["method"] = method;
    const int segments = std::max(1, static_cast<int>(std::lround(2.0 * plane.extent / h)));
    json points = json::array();
    for (int i = 0; i <= segments; ++i) {
      // Along s = (n_y, -n_x) (make_plane), the material on the left.
      const Eigen::Vector3d x =
          plane.origin + (-plane.extent + 2.0 * plane.extent * i / segments) * plane.s;
      points.push_back(vec({x.x(), x.y()}));
    }
    wall["surface"] = {{"type", "polyline"}, {"points", points}};
  } else {
    wall["name"] = "wall";
    wall["method"] = method;
    std::ofstream obj(mesh_file);
    obj.precision(17);
    const double e = plane.extent;
    for (const auto& [a, b] : {std::pair{-1.0, -1.0}, {1.0, -1.0}, {1.0, 1.0}, {-1.0, 1.0}}) {
      const Eigen::Vector3d x = plane.origin + e * (a * plane.s + b * plane.t);
      obj << "v " << x.x() << ' ' << x.y() << ' ' << x.z() << '\n';
    }
    obj << "f 1 2 3\nf 1 3 4\n";  // (b - a) x (c - a) along s x t = n: into the material
    if (!obj) throw std::runtime_error("cannot write " + mesh_file.string());
    wall["surface"] = {{"type", "mesh"}, {"file", mesh_file.string()}, {"remesh", true}};
  }
  doc["walls"] = json::array({wall});
  return doc;
}

/// A box body of size `size` (along s, t, n) with its lowest face `gap` above the plane,
/// centred at `u` along s, turned to lie flat on the plane.
json block_on_plane(int dim, const Plane& plane, const Eigen::Vector3d& size, double gap, double u,
                    const Eigen::Vector3d& velocity, int ppc) {
  const Eigen::Vector3d c = plane.origin + u * plane.s + (gap + 0.5 * size.z()) * plane.normal;
  json shape = {{"type", "box"}};
  if (dim == 2) {
    shape["min"] = vec({c.x() - 0.5 * size.x(), c.y() - 0.5 * size.z()});
    shape["max"] = vec({c.x() + 0.5 * size.x(), c.y() + 0.5 * size.z()});
    shape["rotation"] = std::atan2(plane.s.y(), plane.s.x()) * 180.0 / kPi;
  } else {
    Eigen::Matrix3d R;
    R << plane.s, plane.t, plane.normal;
    const Eigen::Vector3d zyx = R.eulerAngles(2, 1, 0) * (180.0 / kPi);
    shape["min"] = vec({c.x() - 0.5 * size.x(), c.y() - 0.5 * size.y(), c.z() - 0.5 * size.z()});
    shape["max"] = vec({c.x() + 0.5 * size.x(), c.y() + 0.5 * size.y(), c.z() + 0.5 * size.z()});
    shape["rotation"] = vec({zyx[2], zyx[1], zyx[0]});
  }
  json v = json::array();
  for (int d = 0; d < dim; ++d) v.push_back(velocity[d]);
  return {{"material", "m"}, {"shape", shape}, {"particles_per_cell", ppc}, {"velocity", v}};
}

/// A plane through the origin offset by a fraction of h on each axis, normal n.
Plane make_plane(int dim, const Eigen::Vector3d& n, const Eigen::Vector3d& offset, double extent) {
  Plane p;
  p.origin = offset;
  p.normal = n.normalized();
  p.extent = extent;
  if (dim == 2) {
    p.s = Eigen::Vector3d(p.normal.y(), -p.normal.x(), 0.0);
    p.t = Eigen::Vector3d::Zero();
  } else {
    const Eigen::Vector3d any =
        std::abs(p.normal.z()) < 0.9 ? Eigen::Vector3d::UnitZ() : Eigen::Vector3d::UnitX();
    p.s = (any - any.dot(p.normal) * p.normal).normalized();
    p.t = p.normal.cross(p.s);
  }
  return p;
}

/// The wall of a verification incline frame (incline_frame(): at the angle to the grid and off
/// the nodes, or for "grid" the box floor), centred `along` its downhill direction.
Plane plane_of(const Frame2& f, double extent, double along = 0.0) {
  const Eigen::Vector3d down(f.down.x(), f.down.y(), 0.0);
  return make_plane(2, Eigen::Vector3d(f.normal.x(), f.normal.y(), 0.0),
                    Eigen::Vector3d(f.origin.x(), f.origin.y(), 0.0) + along * down, extent);
}

class Stability {
 public:
  Stability(const BenchArgs& args, const json& config) : args_(args), config_(config) {
    work_ = mpm::test::temporary_directory("the stability runs' files") /
            ("mpm_bench_" + std::to_string(::getpid()));
    std::filesystem::create_directories(work_);
    const std::string where = args.config.string() + ": /limits";
    const json limits = config_value<json>(config, "limits", args.config.string() + ": ");
    limits_.penetration = config_value<double>(limits, "penetration", where);
    limits_.energy = config_value<double>(limits, "energy", where);
  }
  ~Stability() {
    std::error_code ec;
    std::filesystem::remove_all(work_, ec);
  }

  int run() {
    static const std::vector<std::string> parts = {"throws", "long", "cfl", "crossing"};
    for (const std::string& name : args_.cases) {
      if (std::find(parts.begin(), parts.end(), name) == parts.end()) {
        throw ConfigError("stability: no part \"" + name + "\" (parts: throws long cfl crossing)");
      }
    }
    if (selected(args_.cases, "throws")) throws();
    if (selected(args_.cases, "long")) long_runs();
    if (selected(args_.cases, "cfl")) cfl_sweep();
    if (selected(args_.cases, "crossing")) crossing();
    return finish();
  }

 private:
  json part(const std::string& name) const {
    const std::string where = args_.config.string() + ": /" + name;
    json p = config_value<json>(config_, name, args_.config.string() + ": ");
    if (args_.smoke) {
      if (!p.contains("smoke")) throw ConfigError(where + "/smoke: missing");
      p.update(p["smoke"]);
    }
    return p;
  }
  std::vector<std::string> methods(const json& p, const std::string& where) const {
    std::vector<std::string> out;
    for (const auto& m : config_value<std::vector<std::string>>(p, "methods", where)) {
      if (selected(args_.methods, m)) out.push_back(m);
    }
    return out;
  }

  /// Runs `doc`, watched by `mon`; fills the outcome and records it (and the scene on failure).
  void record(Outcome o, const json& doc, Monitor mon, const Observer& extra = nullptr,
              std::int64_t max_steps = 0,
              const std::function<void(Outcome&, const Run&, const Monitor&)>& finish = nullptr) {
    o.id = static_cast<int>(outcomes_.size());
    Run r;
    try {
      r = run_scene_doc(
          doc, "bench " + o.part,
          [&](Simulation& sim, double time, double dt) {
            mon.watch(sim, false);
            if (extra) extra(sim, time, dt);
          },
          [&](Simulation& sim) { mon.watch(sim, true); }, max_steps);
      o.fault = r.fault;
    } catch (const std::exception& e) {
      o.fault = std::string("scene rejected: ") + e.what();
    }
    o.steps = r.steps;
    o.seconds = r.seconds;
    mon.judge(o, limits_);
    if (finish && r.sim) finish(o, r, mon);
    if (o.failed()) o.scene_file = write_failure(o, doc);
    std::string extra_text;
    char buffer[96];
    if (!std::isnan(o.creep)) {
      std::snprintf(buffer, sizeof buffer, "  creep %.2e h drift %.2e", o.creep, o.energy_drift);
      extra_text += buffer;
    }
    if (!std::isnan(o.crossings)) {
      std::snprintf(buffer, sizeof buffer, "  crossings/step %.2f error %.2e", o.crossings,
                    o.error);
      extra_text += buffer;
    }
    std::printf(
        "%-8s %4d %-9s %-13s %dD cfl %-4.2g %7lld steps %7.2f s  closest %6.3f h  pen %6.3f h  "
        "dE %9.2e%s%s%s%s\n",
        o.part.c_str(), o.id, o.method.c_str(), o.kernel.c_str(), o.dimension, o.cfl,
        static_cast<long long>(o.steps), o.seconds, o.closest, o.penetration, o.energy_growth,
        extra_text.c_str(), o.failed() ? "  FAIL " : "", o.failed() ? join(o.reasons).c_str() : "",
        o.fault.empty() ? "" : ("  (" + o.fault + ")").c_str());
    std::fflush(stdout);
    outcomes_.push_back(o);
  }

  static std::string join(const std::vector<std::string>& v) {
    std::string s;
    for (const auto& x : v) s += (s.empty() ? "" : "+") + x;
    return s;
  }

  /// Writes a failing run's scene (and its wall mesh) to --failures; returns the scene's path.
  std::string write_failure(const Outcome& o, json doc) {
    std::error_code ec;
    std::filesystem::create_directories(args_.failures, ec);
    const std::string stem = "stability_" + o.part + "_" + std::to_string(o.id);
    for (json& w : doc["walls"]) {
      if (w.contains("surface") && w["surface"].value("type", "") == "mesh") {
        const std::filesystem::path mesh = w["surface"]["file"].get<std::string>();
        const std::filesystem::path copy = args_.failures / (stem + mesh.extension().string());
        std::filesystem::copy_file(mesh, copy, std::filesystem::copy_options::overwrite_existing,
                                   ec);
        w["surface"]["file"] = std::filesystem::absolute(copy).string();
      }
    }
    const std::filesystem::path file = args_.failures / (stem + ".json");
    std::ofstream out(file);
    out << doc.dump(1) << "\n";
    if (!out) {
      std::cerr << "mpm bench: cannot write " << file.string() << "\n";
      write_error_ = true;
    }
    return file.string();
  }

  // (1) Random wall placements, blocks thrown at the wall.
  void throws() {
    const std::string where = args_.config.string() + ": /throws";
    const json p = part("throws");
    std::mt19937_64 rng(args_.seed);
    std::uniform_real_distribution<double> U(0.0, 1.0);
    const int count =
        args_.runs > 0 && !args_.smoke ? args_.runs : config_value<int>(p, "runs", where);
    const double share3d = config_value<double>(p, "share_3d", where);
    const auto ms = methods(p, where);
    if (ms.empty()) return;
    const double h2 = config_value<double>(p, "spacing_2d", where);
    const double h3 = config_value<double>(p, "spacing_3d", where);
    for (int i = 0; i < count; ++i) {
      // Every draw is made whatever the branch, so run i is the same for any --methods.
      const std::string method = ms[static_cast<std::size_t>(i) % ms.size()];
      const bool three = U(rng) < share3d;
      const int dim = three ? 3 : 2;
      const double h = three ? h3 : h2;
      // Normal: uniform on the circle / sphere.
      const double phi = 2 * kPi * U(rng), zc = 2 * U(rng) - 1;
      const Eigen::Vector3d n = three ? Eigen::Vector3d(std::sqrt(1 - zc * zc) * std::cos(phi),
                                                        std::sqrt(1 - zc * zc) * std::sin(phi), zc)
                                      : Eigen::Vector3d(std::cos(phi), std::sin(phi), 0.0);
      const Eigen::Vector3d offset(h * U(rng), h * U(rng), three ? h * U(rng) : 0.0);
      const Eigen::Vector3d size((2 + 4 * U(rng)) * h, (2 + 2 * U(rng)) * h, (2 + 2 * U(rng)) * h);
      const double gap = (0.5 + 1.5 * U(rng)) * h;
      const double vn = 0.5 + 4.5 * U(rng), vs = 3.0 * U(rng) - 1.5, vt = 3.0 * U(rng) - 1.5;
      const double mu = std::array<double, 3>{0.0, 0.3, 1.0}[static_cast<int>(3 * U(rng)) % 3];
      const double E = 2e5 * std::pow(three ? 10.0 : 100.0, U(rng));
      const bool gravity_on = U(rng) < 0.5;
      const double ga = (U(rng) - 0.5) * kPi / 2, gb = 2 * kPi * U(rng);
      const double end = gap / vn + 0.1;
      const double extent = 0.5 * size.x() + 1.5 * end + 0.5 * kGravity * end * end + 2 * h;

      const Plane plane = make_plane(dim, n, offset, extent);
      const Eigen::Vector3d tdir = three ? plane.t : Eigen::Vector3d::Zero();
      const Eigen::Vector3d v = -vn * plane.normal + vs * plane.s + vt * tdir;
      // Gravity into the wall, within 45 degrees of -n.
      Eigen::Vector3d g = Eigen::Vector3d::Zero();
      if (gravity_on) {
        const Eigen::Vector3d side =
            three ? std::cos(gb) * plane.s + std::sin(gb) * plane.t : plane.s;
        g = kGravity * (-std::cos(ga) * plane.normal + std::sin(ga) * side);
      }
      const double height = gap + size.z() + 1.2 * vn * end + 4 * h;
      const json material = elastic(1000.0, E, 0.3, "neo_hookean");
      const json body = block_on_plane(dim, plane, size, gap, 0.0, v, 2);
      const json doc = plane_doc(dim, plane, height, method, h, "bspline2/apic", mu, body, material,
                                 g, end, 0.5, work_ / ("throw_" + std::to_string(i) + ".obj"));
      Outcome o = outcome("throws", method, "bspline2/apic", 0.5, dim);
      char detail[256];
      std::snprintf(detail, sizeof detail,
                    "n (%.3f %.3f %.3f) offset/h (%.2f %.2f %.2f) v (%.2f %.2f %.2f) mu %g E %.3g "
                    "g %s",
                    n.x(), n.y(), n.z(), offset.x() / h, offset.y() / h, offset.z() / h, v.x(),
                    v.y(), v.z(), mu, E, gravity_on ? "on" : "off");
      o.detail = detail;
      const double m = 1000.0 * size.x() * (three ? size.y() : 1.0) * size.z();
      record(o, doc,
             watch(plane, g, h, 0.5 * m * v.squaredNorm() + m * g.norm() * (gap + size.z())));
    }
  }

  // (2) 10^5 steps of a block resting on a frictional incline (mu > tan theta: it sticks).
  void long_runs() {
    const std::string where = args_.config.string() + ": /long";
    const json p = part("long");
    const double theta = config_value<double>(p, "angle", where);
    const double mu = config_value<double>(p, "friction", where);
    const double h = config_value<double>(p, "spacing", where);
    const auto steps = config_value<std::int64_t>(p, "steps", where);
    const double creep_limit = config_value<double>(p, "creep", where);
    for (const std::string& method : methods(p, where)) {
      const double th = theta * kPi / 180.0;
      // The wall at theta to the grid (grid: on the box floor, gravity turned instead).
      const Plane plane = plane_of(incline_frame(theta, method), 0.6);
      // s runs downhill when n leans towards +x: gravity along -n and +s.
      const Eigen::Vector3d g = kGravity * (-std::cos(th) * plane.normal + std::sin(th) * plane.s);
      const Eigen::Vector3d size(0.3, 0.0, 0.15);
      const json body = block_on_plane(2, plane, size, 1e-6, 0.0, Eigen::Vector3d::Zero(), 2);
      const json doc =
          plane_doc(2, plane, 0.4, method, h, "bspline2/apic", mu, body,
                    elastic(1000.0, 2e6, 0.3, "neo_hookean"), g, 1e6, 0.5, work_ / "long.obj");
      Outcome o = outcome("long", method, "bspline2/apic", 0.5);
      char detail[128];
      std::snprintf(detail, sizeof detail, "theta %g mu %g (tan %.3f) %lld steps", theta, mu,
                    std::tan(th), static_cast<long long>(steps));
      o.detail = detail;
      const double m = 1000.0 * size.x() * size.z();  // scale: its weight times its height
      record(o, doc, watch(plane, g, h, m * kGravity * size.z()), nullptr, steps,
             [&](Outcome& out, const Run&, const Monitor& w) {
               // Exact: it sticks. Creep is the centre of mass's travel along the slope.
               out.creep = std::abs((w.com - w.com0).dot(plane.s)) / h;
               if (!(out.creep <= creep_limit)) out.reasons.push_back("creep");
               if (out.steps < steps && out.fault.empty()) out.reasons.push_back("short");
             });
    }
  }

  // (3) CFL sweep: a block thrown at a wall at an angle to the grid, under gravity, with
  // friction; the largest CFL number at which it (and every smaller one) passes.
  void cfl_sweep() {
    const std::string where = args_.config.string() + ": /cfl";
    const json p = part("cfl");
    const auto numbers = config_value<std::vector<double>>(p, "cfl", where);
    // "shape function/transfer": the CFL limit depends on both.
    const auto kernels = config_value<std::vector<std::string>>(p, "kernels", where);
    for (const std::string& k : kernels) {
      if (k.find('/') == std::string::npos) {
        throw ConfigError(where + "/kernels: \"" + k + "\" is not \"shape/transfer\"");
      }
    }
    const double theta = config_value<double>(p, "angle", where);
    const double h = config_value<double>(p, "spacing", where);
    for (const std::string& method : methods(p, where)) {
      for (const std::string& kernel : kernels) {
        double largest = 0.0;
        bool stable = true;
        for (const double cfl : numbers) {
          const double th = theta * kPi / 180.0;
          const Plane plane = plane_of(incline_frame(theta, method), 1.2);
          const Eigen::Vector3d g =
              kGravity * (-std::cos(th) * plane.normal + std::sin(th) * plane.s);
          const Eigen::Vector3d v = -3.0 * plane.normal + 1.0 * plane.s;
          const Eigen::Vector3d size(0.3, 0.0, 0.15);
          const double gap = 2.0 * h, end = 0.25;
          const json body = block_on_plane(2, plane, size, gap, -0.3, v, 2);
          const json doc =
              plane_doc(2, plane, 1.2, method, h, kernel, 0.3, body,
                        elastic(1000.0, 2e6, 0.3, "neo_hookean"), g, end, cfl, work_ / "cfl.obj");
          Outcome o = outcome("cfl", method, kernel, cfl);
          o.detail = "theta " + std::to_string(theta) + " v (-3 n + 1 s) mu 0.3";
          const double m = 1000.0 * size.x() * size.z();
          const Monitor mon =
              watch(plane, g, h, 0.5 * m * v.squaredNorm() + m * kGravity * (gap + size.z()));
          record(o, doc, mon);
          if (outcomes_.back().failed()) stable = false;
          if (stable) largest = cfl;
        }
        largest_cfl_[method + " " + kernel] = largest;
      }
    }
  }

  // (4) Particles crossing Phi between the layer and the bulk: a disk turning on a wall keeps
  // carrying its particles into and out of the layer. Two scenes with exact answers: a disk
  // rolling down an incline (mu >= tan(theta) / 3: d = g sin(theta) t^2 / 3), and a "bowling"
  // disk launched along a floor at an angle to the grid at v0 without spin, which slides while
  // friction spins it up and rolls at 2 v0 / 3 from t* = v0 / (3 mu g) on. Energy can only fall.
  void crossing() {
    const std::string where = args_.config.string() + ": /crossing";
    const json p = part("crossing");
    const double h = config_value<double>(p, "spacing", where);
    const double end = config_value<double>(p, "time", where);
    const double tolerance = config_value<double>(p, "tolerance", where);
    const double mu = config_value<double>(p, "friction", where);
    const double R = 0.2, m = 1000.0 * kPi * R * R;
    auto disk = [&](const Eigen::Vector3d& c, const Eigen::Vector3d& v) {
      return json{{"material", "m"},
                  {"shape", {{"type", "disk"}, {"center", vec({c.x(), c.y()})}, {"radius", R}}},
                  {"particles_per_cell", 4},
                  {"velocity", vec({v.x(), v.y()})}};
    };
    for (const std::string& method : methods(p, where)) {
      for (const double theta : config_value<std::vector<double>>(p, "angles", where)) {
        const double th = theta * kPi / 180.0;
        if (mu < std::tan(th) / 3.0) throw ConfigError(where + "/friction: the disk would slip");
        const Frame2 f = incline_frame(theta, method);
        const Plane plane = plane_of(f, 1.0, 1.0);  // the wall runs from 0 to 2 along f.down
        const Eigen::Vector3d c = plane.origin - 0.6 * plane.s + (R + 1e-6) * plane.normal;
        json doc = incline_doc_2d(f, theta, method, h, 0.0, 2.0, disk(c, Eigen::Vector3d::Zero()),
                                  mu, end, {{"update", "musl"}, {"transfer", "apic"}});
        doc["time"]["cfl"] = 0.5;
        const Eigen::Vector3d g(doc["gravity"][0].get<double>(), doc["gravity"][1].get<double>(),
                                0.0);
        char detail[96];
        std::snprintf(detail, sizeof detail, "rolling disk R %g on %g degrees, mu %g", R, theta,
                      mu);
        const double travel = kGravity * std::sin(th) * end * end / 3.0;
        run_crossing(method, detail, doc, plane, g, h, m * kGravity * 2.0 * R, travel, -1.0,
                     tolerance);
      }
      const double tilt_deg = config_value<double>(p, "bowling_tilt", where);
      const double v0 = config_value<double>(p, "bowling_speed", where);
      const double length = config_value<double>(p, "bowling_length", where);
      const double bowling_end = config_value<double>(p, "bowling_time", where);
      const Plane plane = plane_of(incline_frame(tilt_deg, method), 0.5 * length);
      const Eigen::Vector3d g = -kGravity * plane.normal;
      const Eigen::Vector3d c =
          plane.origin - (0.5 * length - R - 2 * h) * plane.s + (R + 1e-6) * plane.normal;
      const json doc = plane_doc(2, plane, 4 * R, method, h, "bspline2/apic", mu,
                                 disk(c, v0 * plane.s), elastic(1000.0, 2e6, 0.3, "neo_hookean"), g,
                                 bowling_end, 0.5, work_ / "bowling.obj");
      const double t_roll = v0 / (3.0 * mu * kGravity);
      const double travel = bowling_end <= t_roll
                                ? v0 * bowling_end - 0.5 * mu * kGravity * bowling_end * bowling_end
                                : v0 * t_roll - 0.5 * mu * kGravity * t_roll * t_roll +
                                      2.0 / 3.0 * v0 * (bowling_end - t_roll);
      const double speed =
          bowling_end <= t_roll ? v0 - mu * kGravity * bowling_end : 2.0 * v0 / 3.0;
      char detail[128];
      std::snprintf(
          detail, sizeof detail,
          "bowling disk R %g at %g m/s on a floor at %g degrees, mu %g (rolls from %.3f s)", R, v0,
          tilt_deg, mu, t_roll);
      run_crossing(method, detail, doc, plane, g, h, 0.5 * m * v0 * v0, travel, speed, tolerance);
    }
  }

  /// One crossing run: counts the particles that change owner each step; checks the travel
  /// along plane.s (and the final speed, if > 0) against the exact values.
  void run_crossing(const std::string& method, const std::string& detail, const json& doc,
                    const Plane& plane, const Eigen::Vector3d& g, double h, double scale,
                    double exact_travel, double exact_speed, double tolerance) {
    Outcome o = outcome("crossing", method, "bspline2/apic", doc["time"]["cfl"].get<double>());
    o.detail = detail;
    const Monitor mon = watch(plane, g, h, scale);
    std::vector<int> owner;
    std::int64_t crossings = 0, steps_with = 0, steps = 0;
    double travel = 0.0, mass = 0.0, speed = 0.0;
    const Observer count = [&](Simulation& sim, double, double dt) {
      if (mass == 0.0) mass = total_mass(sim);
      speed = sim.momentum().dot(plane.s) / mass;
      travel += speed * dt;
      auto* solver = dynamic_cast<Solver<2>*>(&sim);
      if (solver == nullptr) return;
      const std::vector<int>& now = solver->particles.layer_wall;
      if (owner.size() == now.size()) {
        std::int64_t changed = 0;
        for (std::size_t i = 0; i < now.size(); ++i) changed += owner[i] != now[i] ? 1 : 0;
        crossings += changed;
        steps_with += changed > 0 ? 1 : 0;
        ++steps;
      }
      owner = now;
    };
    record(o, doc, mon, count, 0, [&](Outcome& out, const Run&, const Monitor&) {
      out.crossings = steps > 0 ? static_cast<double>(crossings) / steps : 0.0;
      out.detail +=
          "; steps with a crossing " + std::to_string(steps_with) + " of " + std::to_string(steps);
      out.error = std::abs(travel / exact_travel - 1.0);
      if (exact_speed > 0.0) {
        out.error = std::max(out.error, std::abs(speed / exact_speed - 1.0));
      }
      if (!(out.error <= tolerance)) out.reasons.push_back("travel");
      if (method != "grid" && method != "sdf" && steps_with == 0) {
        out.reasons.push_back("no crossing");
      }
    });
  }

  int finish() {
    std::size_t failed = 0;
    std::map<std::string, std::pair<int, int>> by_part;  // runs, failures
    for (const Outcome& o : outcomes_) {
      by_part[o.part].first += 1;
      by_part[o.part].second += o.failed() ? 1 : 0;
      failed += o.failed() ? 1 : 0;
    }
    for (const auto& [name, counts] : by_part) {
      std::printf("%-8s %4d runs, %d failed\n", name.c_str(), counts.first, counts.second);
    }
    for (const auto& [key, cfl] : largest_cfl_) {
      std::printf("largest stable CFL  %-18s %.2g\n", key.c_str(), cfl);
    }
    if (!args_.csv_file.empty() || !args_.plot_file.empty()) {
      std::filesystem::path csv = args_.csv_file;
      if (csv.empty()) csv = work_ / "stability.csv";
      std::ofstream out(csv);
      out << "part,id,method,kernel,dimension,cfl,steps,seconds,closest_h,penetration_h,energy_"
             "growth,"
             "energy_drift,creep_h,crossings_per_step,error,failed,reasons,fault,detail,scene\n";
      out.precision(9);
      for (const Outcome& o : outcomes_) {
        out << o.part << ',' << o.id << ',' << o.method << ',' << o.kernel << ',' << o.dimension
            << ',' << o.cfl << ',' << o.steps << ',' << o.seconds << ',' << o.closest << ','
            << o.penetration << ',' << o.energy_growth << ',' << o.energy_drift << ',' << o.creep
            << ',' << o.crossings << ',' << o.error << ',' << (o.failed() ? 1 : 0) << ','
            << join(o.reasons) << ',' << quoted(o.fault) << ',' << quoted(o.detail) << ','
            << quoted(o.scene_file) << '\n';
      }
      if (!out) {
        std::cerr << "mpm bench: cannot write " << csv.string() << "\n";
        return kExitIo;
      }
      out.close();
      if (!args_.plot_file.empty() && !plot(args_, csv)) return kExitIo;
    }
    if (write_error_) return kExitIo;
    std::printf("%zu runs, %zu failed%s\n", outcomes_.size(), failed,
                failed ? (" (scenes in " + args_.failures.string() + ")").c_str() : "");
    return failed == 0 ? 0 : 1;
  }

  const BenchArgs& args_;
  const json& config_;
  Limits limits_;
  std::filesystem::path work_;
  std::vector<Outcome> outcomes_;
  std::map<std::string, double> largest_cfl_;
  bool write_error_ = false;
};

}  // namespace

int bench_command(const BenchArgs& args) {
  json config;
  try {
    std::ifstream in(args.config);
    if (!in) throw std::runtime_error("cannot be read");
    config = json::parse(in);
  } catch (const std::exception& e) {
    std::cerr << "mpm bench: " << args.config.string() << ": " << e.what() << "\n";
    return kExitBadInput;
  }
  try {
    if (args.kind == "accuracy") return accuracy(args, config);
    Stability stability(args, config);
    return stability.run();
  } catch (const ConfigError& e) {
    std::cerr << "mpm bench: " << e.what() << "\n";
    return kExitBadInput;
  } catch (const std::exception& e) {  // its files: the temporary directory, a CSV, a scene's
    std::cerr << "mpm bench " << args.kind << ": " << e.what() << "\n";
    return kExitIo;
  }
}

}  // namespace mpm::tools
