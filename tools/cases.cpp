// The verification cases (DESIGN.md section 5): a checker per case that builds the scene for one
// wall method and resolution, runs it, and measures the error against the exact answer; the
// parameters are in data/verification/<case>.json.
//
// Wall methods: "grid" (standard MPM, the wall on a box face: the scene is turned so the wall is
// grid-aligned, gravity with it), "sdf" (signed-distance baseline on the standard grid),
// "one-way" and "mortar" (Blending), "enhanced". A case lists the ones that apply.

#include <unistd.h>
#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <numbers>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "cases.hpp"
#include "mpm/solver.hpp"
#include "support/temp_directory.hpp"

namespace mpm::tools {

using nlohmann::json;
constexpr double kGravity = 9.81;
constexpr double kPi = std::numbers::pi;

/// --scenes DIR: where run_scene_doc writes each scene, named after the case, method and
/// resolution running (set by verify_command) and a count within them.
namespace {

struct SceneDump {
  std::filesystem::path dir;
  std::string prefix;
  int count = 0;
} g_dump;

/// --multiplier-radius: given to every Blending wall (mortar, one-way) of the cases run.
double g_multiplier_radius = 0.0;
/// --update: the update scheme of every case run (empty: the case's own).
std::string g_update;

}  // namespace

void dump_scenes(const std::filesystem::path& dir, const std::string& prefix) {
  g_dump.dir = dir;
  g_dump.prefix = prefix;
  g_dump.count = 0;
}

void merge_multipliers(double radius) { g_multiplier_radius = radius; }
void use_update_scheme(const std::string& update) { g_update = update; }

Run run_scene_doc(const json& case_doc, const std::string& label, const Observer& observe,
                  const std::function<void(Simulation&)>& start, std::int64_t max_steps) {
  json doc = case_doc;
  if (g_multiplier_radius > 0.0 && doc.contains("walls")) {
    for (json& wall : doc["walls"]) {
      const std::string method = wall.value("method", "");
      if (method == "mortar" || method == "one-way")
        wall["multiplier_radius"] = g_multiplier_radius;
    }
  }
  if (!g_update.empty()) {
    const std::string shape = doc.value("shape_function", "bspline2");
    if (g_update == "mls" && shape != "bspline2") {
      throw NotApplicable("MLS-MPM needs the quadratic B-spline; this case runs the " + shape +
                          " kernel");
    }
    const std::string transfer = doc["scheme"].value("transfer", "apic");
    if (g_update == "mls" && transfer != "apic") {
      throw NotApplicable("MLS-MPM needs APIC; this case runs " + transfer);
    }
    doc["scheme"]["update"] = g_update;
  }
  Run r;
  const auto clock_start = std::chrono::steady_clock::now();
  if (!g_dump.dir.empty()) {
    // --scenes: every scene as a file `mpm run` takes, to rerun one configuration alone.
    const auto file = g_dump.dir / (g_dump.prefix + "_" + std::to_string(g_dump.count++) + ".json");
    std::ofstream out(file);
    out << doc.dump(1) << "\n";
    if (!out) throw std::runtime_error("cannot write " + file.string());
  }
  r.scene = parse_scene(doc, "<" + label + ">");
  r.sim = make_simulation(r.scene);
  if (start) start(*r.sim);
  double t = 0.0;
  const double end = r.scene.end_time;
  while (t < end - 1e-12 * end && (max_steps <= 0 || r.steps < max_steps)) {
    const double dt = std::min(r.sim->stable_dt(r.scene.cfl), end - t);
    r.sim->step(dt);
    t += dt;
    ++r.steps;
    if (r.sim->fault()) {
      r.fault = "t = " + std::to_string(t) + ": " + *r.sim->fault();
      break;
    }
    if (observe) observe(*r.sim, t, dt);
  }
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - clock_start).count();
  return r;
}

json vec(std::initializer_list<double> v) { return json(std::vector<double>(v)); }

json contact(double mu, bool separable) {
  json c = {{"separable", separable}};
  if (mu > 0.0) {
    c["condition"] = "friction";
    c["mu"] = mu;
  } else {
    c["condition"] = "slip";
  }
  return c;
}

json elastic(double density, double youngs, double poisson, const std::string& model) {
  json m = {{"name", "m"}, {"model", model}, {"density", density}, {"youngs_modulus", youngs}};
  if (poisson >= 0.0) m["poisson_ratio"] = poisson;
  return m;
}

namespace {

double param(const json& p, const char* key) {
  if (!p.contains(key) || !p[key].is_number()) {
    throw std::runtime_error(std::string("parameter \"") + key + "\" missing or not a number");
  }
  return p[key].get<double>();
}

// ---------------------------------------------------------------------------------------------
// 1D cases: the wall is a point at an arbitrary offset from the nodes (grid: on a node).

/// Steel bar against a rigid wall: stress rho c v0 for 2L/c, rebound at v0.
std::vector<Check> bar_impact(const json& p, const std::string& method, int k) {
  const double h = param(p, "spacing") / k, offset = param(p, "offset");
  const double E = 2e11, rho = 7850.0, L = 1.0, v0 = 1.0, c = std::sqrt(E / rho);
  const double T = 2.0 * L / c, sigma = rho * c * v0, x0 = 0.2;
  const double xw = method == "grid" ? x0 : x0 + offset * h;
  json doc = {
      {"dimension", 1},
      {"grid", {{"min", vec({method == "grid" ? x0 : 0.0})}, {"max", vec({1.5})}, {"spacing", h}}},
      {"shape_function", p.value("shape", "linear")},
      {"scheme", {{"update", "musl"}, {"transfer", "apic"}}},
      {"materials", json::array({elastic(rho, E, -1.0, "linear_elastic")})},
      {"bodies",
       {{{"material", "m"},
         {"shape",
          {{"type", "segment"}, {"min", vec({xw})}, {"max", vec({xw + L})}, {"lattice", "body"}}},
         {"particles_per_cell", 2},
         {"velocity", vec({-v0})}}}},
      {"time", {{"end", 1.5 * T}, {"cfl", 0.5}}}};
  if (method == "grid") {
    doc["walls"] = {{{"face", "xmin"}, {"condition", "slip"}, {"separable", true}}};
  } else {
    json w = contact(0.0, true);
    w["name"] = "wall";
    w["method"] = method;
    w["surface"] = {{"type", "point"}, {"position", xw}, {"side", 1}};
    doc["walls"] = json::array({w});
  }
  double plateau = 0.0, time = 0.0;
  Run r = run_scene_doc(doc, "bar_impact_1d", [&](Simulation& s, double t, double dt) {
    const double stress = s.wall_impulses()[0][0] / dt / sigma;
    s.reset_wall_impulses();
    if (t > 0.2 * T && t < 0.8 * T) {
      plateau += stress * dt;
      time += dt;
    }
  });
  const double mass = rho * L;
  const double tol = param(p, "tolerance");
  Check a{
      "bar_impact_1d", method, "|plateau/(rho c v0) - 1|", k, std::abs(plateau / time - 1.0), tol,
      r.seconds};
  Check b{"bar_impact_1d",
          method,
          "|rebound/v0 - 1|",
          k,
          std::abs(r.sim->momentum()[0] / mass / v0 - 1.0),
          tol,
          r.seconds};
  for (Check* c2 : {&a, &b}) c2->note = r.fault;
  return {a, b};
}

/// Axial vibration of a bar fixed at one end: v_cm = v0 / (beta L) cos(omega t).
std::vector<Check> axial_vibration(const json& p, const std::string& method, int k) {
  const double E = 100.0, rho = 1.0, L = 25.0, v0 = 0.1, beta = kPi / (2.0 * L);
  const double omega = beta * std::sqrt(E / rho), h = param(p, "spacing") / k;
  const double offset = param(p, "offset");
  const double x0 = method == "grid" ? 0.0 : 0.0 + offset * h;
  json body = {
      {"material", "m"},
      {"shape",
       {{"type", "segment"}, {"min", vec({x0})}, {"max", vec({x0 + L})}, {"lattice", "body"}}},
      // 2 per cell: with 1, a particle near the free end crosses into an empty cell
      // and the linear kernel lets the bar come apart there (cell crossing).
      {"particles_per_cell", 2},
      {"velocity_sine", {{"amplitude", vec({v0})}, {"wavenumber", beta}, {"origin", x0}}}};
  json doc = {
      {"dimension", 1},
      {"grid",
       {{"min", vec({method == "grid" ? 0.0 : -2.0})}, {"max", vec({30.0})}, {"spacing", h}}},
      {"shape_function", "bspline2"},
      {"scheme", {{"update", "musl"}, {"transfer", "apic"}}},
      {"materials", json::array({elastic(rho, E, -1.0, "linear_elastic")})},
      {"bodies", json::array({body})},
      {"time", {{"end", 2.0 * 2.0 * kPi / omega}, {"cfl", 0.5}}}};
  if (method == "grid") {
    doc["walls"] = {{{"face", "xmin"}, {"condition", "sticky"}}};
  } else {
    doc["walls"] = {{{"name", "end"},
                     {"method", method},
                     {"condition", "sticky"},
                     {"separable", false},
                     {"surface", {{"type", "point"}, {"position", x0}, {"side", 1}}}}};
  }
  const double amplitude = v0 / (beta * L), mass = rho * L;
  double worst = 0.0;
  Run r = run_scene_doc(doc, "axial_vibration_1d", [&](Simulation& s, double t, double) {
    const double v = s.momentum()[0] / mass;
    worst = std::max(worst, std::abs(v - amplitude * std::cos(omega * t)));
  });
  Check c{"axial_vibration_1d",  method,   "max|v_cm - exact|/amplitude", k, worst / amplitude,
          param(p, "tolerance"), r.seconds};
  c.note = r.fault;
  return {c};
}

// ---------------------------------------------------------------------------------------------
}  // namespace

// ---------------------------------------------------------------------------------------------
// 2D and 3D cases on an incline at angle theta to the grid. The "grid" method keeps the wall
// on the box floor and turns gravity instead (the same physics in the wall's frame).

Frame2 incline_frame(double theta_deg, const std::string& method) {
  const double th = theta_deg * kPi / 180.0;
  Frame2 f;
  if (method == "grid") {
    f.origin = Eigen::Vector2d(0.0, 0.0);
    f.down = Eigen::Vector2d(1.0, 0.0);
    f.normal = Eigen::Vector2d(0.0, 1.0);
  } else {
    f.origin = Eigen::Vector2d(0.013, 0.027);
    f.down = Eigen::Vector2d(std::cos(th), -std::sin(th));
    f.normal = Eigen::Vector2d(std::sin(th), std::cos(th));
  }
  return f;
}

/// The 2D scene skeleton: a wall along `f` from u0 to u1 (downhill), grid box around it, the
/// given body and gravity making angle theta with the wall's normal.
json incline_doc_2d(const Frame2& f, double theta_deg, const std::string& method, double h,
                    double u0, double u1, const json& body, double mu, double end,
                    const json& scheme) {
  const double th = theta_deg * kPi / 180.0;
  // Gravity: -g (cos theta n - sin theta d), i.e. down the slope with the slope's own angle.
  const Eigen::Vector2d g = -kGravity * (std::cos(th) * f.normal - std::sin(th) * f.down);
  Eigen::Vector2d lo = f.origin + u0 * f.down, hi = lo;
  for (const Eigen::Vector2d& x : {Eigen::Vector2d(f.origin + u1 * f.down),
                                   Eigen::Vector2d(f.origin + u0 * f.down + 0.6 * f.normal),
                                   Eigen::Vector2d(f.origin + u1 * f.down + 0.6 * f.normal)}) {
    lo = lo.cwiseMin(x);
    hi = hi.cwiseMax(x);
  }
  for (int d = 0; d < 2; ++d) {
    lo[d] = h * (std::floor(lo[d] / h) - 4);
    hi[d] = h * (std::ceil(hi[d] / h) + 4);
  }
  json doc = {
      {"dimension", 2},
      {"grid", {{"min", vec({lo.x(), lo.y()})}, {"max", vec({hi.x(), hi.y()})}, {"spacing", h}}},
      {"shape_function", "bspline2"},
      {"scheme", scheme},
      {"gravity", vec({g.x(), g.y()})},
      {"materials", json::array({elastic(1000.0, 2e6, 0.3, "neo_hookean")})},
      {"bodies", json::array({body})},
      {"time", {{"end", end}, {"cfl", 0.4}}}};
  if (method == "grid") {
    doc["grid"]["min"][1] = 0.0;  // the floor on the box face y = 0
    json w = contact(mu, true);
    w["face"] = "ymin";
    doc["walls"] = json::array({w});
  } else {
    json w = contact(mu, true);
    w["name"] = "incline";
    w["method"] = method;
    const int segments = std::max(1, static_cast<int>(std::lround((u1 - u0) / h)));
    json points = json::array();
    for (int i = 0; i <= segments; ++i) {
      const Eigen::Vector2d x = f.origin + (u0 + (u1 - u0) * i / segments) * f.down;
      points.push_back(vec({x.x(), x.y()}));
    }
    w["surface"] = {{"type", "polyline"}, {"points", points}};
    doc["walls"] = json::array({w});
  }
  return doc;
}

double total_mass(const Simulation& s) {
  const ParticleFrame f = s.frame(0.0, 0);
  double m = 0.0;
  for (double mp : f.mass) m += mp;
  return m;
}

namespace {

/// Runs an incline scene; `travel` is the centre of mass's displacement along f.down over the
/// run, integrated from the momentum history.
Run run_downhill(const json& doc, const Frame2& f, const std::string& label, double& travel) {
  Eigen::Vector3d down;
  down << f.down, 0.0;
  double mass = 0.0;
  travel = 0.0;
  return run_scene_doc(doc, label, [&](Simulation& s, double, double dt) {
    if (mass == 0.0) mass = total_mass(s);
    travel += s.momentum().dot(down) / mass * dt;
  });
}

/// Block sliding on an incline: d = a t^2 / 2, a = g (sin - mu cos) if tan > mu.
std::vector<Check> incline_block_2d(const json& p, const std::string& method, int k) {
  std::vector<Check> out;
  const double h = param(p, "spacing") / k, T = param(p, "time");
  for (const double theta : p.at("angles").get<std::vector<double>>()) {
    for (const double mu : p.at("friction").get<std::vector<double>>()) {
      const Frame2 f = incline_frame(theta, method);
      const double a = 0.3, b = 0.15;
      const Eigen::Vector2d c = f.origin + 0.45 * f.down + (0.5 * b + 1e-6) * f.normal;
      const double rot = method == "grid" ? 0.0 : -theta;
      json body = {{"material", "m"},
                   {"shape",
                    {{"type", "box"},
                     {"min", vec({c.x() - 0.5 * a, c.y() - 0.5 * b})},
                     {"max", vec({c.x() + 0.5 * a, c.y() + 0.5 * b})},
                     {"rotation", rot}}},
                   {"particles_per_cell", 2}};
      const json doc = incline_doc_2d(f, theta, method, h, 0.0, 1.5, body, mu, T,
                                      {{"update", "musl"}, {"transfer", "apic"}});
      double travel = 0.0;
      const Run r = run_downhill(doc, f, "incline_block_2d", travel);
      const double th = theta * kPi / 180.0;
      const double accel = kGravity * (std::sin(th) - mu * std::cos(th));
      const double exact = std::tan(th) > mu ? 0.5 * accel * T * T : 0.0;
      char label[64];
      std::snprintf(label, sizeof label, "theta %g mu %g: |d/d_exact - 1|", theta, mu);
      Check ch{"incline_block_2d",
               method,
               label,
               k,
               exact > 0 ? std::abs(travel / exact - 1.0) : std::abs(travel),
               param(p, "tolerance"),
               r.seconds};
      ch.note = r.fault;
      out.push_back(ch);
    }
  }
  return out;
}

/// The 3D incline: a plane tilted by theta about the horizontal axis (cos 30, sin 30, 0), so its
/// normal has three non-zero components, written as a two-triangle OBJ (remeshed to h by the
/// scene reader); the block rotated to lie flat on it. "grid": the floor on the box face z = 0,
/// gravity turned.
std::vector<Check> incline_block_3d(const json& p, const std::string& method, int k) {
  std::vector<Check> out;
  const double h = param(p, "spacing") / k, T = param(p, "time");
  const std::filesystem::path dir = mpm::test::temporary_directory("the 3D incline's meshes") /
                                    ("mpm_verify_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  for (const double theta : p.at("angles").get<std::vector<double>>()) {
    for (const double mu : p.at("friction").get<std::vector<double>>()) {
      const double th = theta * kPi / 180.0, phi = 30.0 * kPi / 180.0;
      Eigen::Vector3d origin(0.013, 0.027, 0.011), n = Eigen::Vector3d::UnitZ();
      if (method != "grid") {
        n = Eigen::AngleAxisd(th, Eigen::Vector3d(std::cos(phi), std::sin(phi), 0.0)) * n;
      } else {
        origin.setZero();
      }
      // Downhill in the plane; for "grid" any in-plane direction, gravity is turned to match.
      const Eigen::Vector3d s =
          method == "grid" ? Eigen::Vector3d::UnitX()
                           : Eigen::Vector3d(-Eigen::Vector3d::UnitZ() + n.z() * n).normalized();
      const Eigen::Vector3d t = n.cross(s);
      const Eigen::Vector3d g = -kGravity * (std::cos(th) * n - std::sin(th) * s);
      const double a = 0.3, b = 0.2, c = 0.15, u0 = -0.25, u1 = 0.7, w = 0.2;
      const Eigen::Vector3d corners[4] = {origin + u0 * s - w * t, origin + u1 * s - w * t,
                                          origin + u1 * s + w * t, origin + u0 * s + w * t};
      Eigen::Vector3d lo = corners[0], hi = corners[0];
      for (const auto& x : corners) {
        lo = lo.cwiseMin(x).cwiseMin(x + 0.3 * n);
        hi = hi.cwiseMax(x).cwiseMax(x + 0.3 * n);
      }
      for (int d = 0; d < 3; ++d) {
        lo[d] = h * (std::floor(lo[d] / h) - 2);
        hi[d] = h * (std::ceil(hi[d] / h) + 2);
      }
      Eigen::Matrix3d R;
      R << s, t, n;
      const Eigen::Vector3d zyx = R.eulerAngles(2, 1, 0) * (180.0 / kPi);
      const Eigen::Vector3d centre = origin + (0.5 * c + 1e-6) * n;
      json body = {
          {"material", "m"},
          {"shape",
           {{"type", "box"},
            {"min", vec({centre.x() - 0.5 * a, centre.y() - 0.5 * b, centre.z() - 0.5 * c})},
            {"max", vec({centre.x() + 0.5 * a, centre.y() + 0.5 * b, centre.z() + 0.5 * c})},
            {"rotation", vec({zyx[2], zyx[1], zyx[0]})}}},
          {"particles_per_cell", 2}};
      json doc = {{"dimension", 3},
                  {"grid",
                   {{"min", vec({lo.x(), lo.y(), method == "grid" ? 0.0 : lo.z()})},
                    {"max", vec({hi.x(), hi.y(), hi.z()})},
                    {"spacing", h}}},
                  {"shape_function", "bspline2"},
                  {"scheme", {{"update", "musl"}, {"transfer", "apic"}}},
                  {"gravity", vec({g.x(), g.y(), g.z()})},
                  {"materials", json::array({elastic(1000.0, 2e6, 0.3, "neo_hookean")})},
                  {"bodies", json::array({body})},
                  {"time", {{"end", T}, {"cfl", 0.4}}}};
      json wall = contact(mu, true);
      if (method == "grid") {
        wall["face"] = "zmin";
      } else {
        const std::filesystem::path mesh =
            dir / ("incline_" + std::to_string(static_cast<int>(theta)) + ".obj");
        std::ofstream obj(mesh);
        obj.precision(17);
        for (const auto& x : corners) obj << "v " << x.x() << ' ' << x.y() << ' ' << x.z() << '\n';
        obj << "f 1 2 3\nf 1 3 4\n";  // (b - a) x (c - a) along +n: into the material
        obj.close();
        wall["name"] = "incline";
        wall["method"] = method;
        wall["surface"] = {{"type", "mesh"}, {"file", mesh.string()}, {"remesh", true}};
      }
      doc["walls"] = json::array({wall});
      Eigen::Vector3d down = s;
      double mass = 0.0, travel = 0.0, window = 0.0;
      // The wall's reaction, averaged from 0.1 T (past the first settling swings) to T.
      Eigen::Vector3d impulse = Eigen::Vector3d::Zero();
      const Run r =
          run_scene_doc(doc, "incline_block_3d", [&](Simulation& sim, double time, double dt) {
            if (mass == 0.0) mass = total_mass(sim);
            travel += sim.momentum().dot(down) / mass * dt;
            if (time > 0.1 * T) {
              for (const Eigen::Vector3d& j : sim.wall_impulses()) impulse += j;
              window += dt;
            }
            sim.reset_wall_impulses();
          });
      const double accel = kGravity * (std::sin(th) - mu * std::cos(th));
      const double exact = 0.5 * accel * T * T;
      char label[64];
      std::snprintf(label, sizeof label, "theta %g mu %g: |d/d_exact - 1|", theta, mu);
      Check ch{"incline_block_3d",    method,   label, k, std::abs(travel / exact - 1.0),
               param(p, "tolerance"), r.seconds};
      ch.note = r.fault;
      out.push_back(ch);
      if (p.contains("reaction_tolerance")) {
        // Sliding, the wall carries the normal weight and Coulomb friction up the slope:
        // R = m g cos(theta) (n - mu s), whatever the block's elastic swings average to.
        const Eigen::Vector3d exact_force = mass * kGravity * std::cos(th) * (n - mu * s);
        const Eigen::Vector3d force = impulse / std::max(window, 1e-300);
        std::snprintf(label, sizeof label, "theta %g mu %g: |R - R_exact|/(m g)", theta, mu);
        Check rc{"incline_block_3d",
                 method,
                 label,
                 k,
                 (force - exact_force).norm() / (mass * kGravity),
                 param(p, "reaction_tolerance"),
                 r.seconds};
        rc.note = r.fault;
        out.push_back(rc);
      }
    }
  }
  std::error_code ec;
  std::filesystem::remove_all(dir, ec);
  return out;
}

/// Rolling cylinder (a disk in 2D): rolls with a = 2/3 g sin if mu >= tan/3, else slides with
/// a = g (sin - mu cos).
std::vector<Check> rolling_cylinder_2d(const json& p, const std::string& method, int k) {
  std::vector<Check> out;
  const double h = param(p, "spacing") / k, T = param(p, "time"), theta = param(p, "angle");
  const double R = param(p, "radius");
  for (const double mu : p.at("friction").get<std::vector<double>>()) {
    const Frame2 f = incline_frame(theta, method);
    const Eigen::Vector2d c = f.origin + 0.4 * f.down + (R + 1e-6) * f.normal;
    json body = {{"material", "m"},
                 {"shape", {{"type", "disk"}, {"center", vec({c.x(), c.y()})}, {"radius", R}}},
                 {"particles_per_cell", static_cast<int>(param(p, "particles_per_cell"))}};
    const json doc = incline_doc_2d(f, theta, method, h, 0.0, 2.0, body, mu, T,
                                    {{"update", "musl"}, {"transfer", "apic"}});
    double travel = 0.0;
    const Run r = run_downhill(doc, f, "rolling_cylinder_2d", travel);
    const double th = theta * kPi / 180.0;
    const bool rolls = mu >= std::tan(th) / 3.0;
    const double accel =
        rolls ? 2.0 / 3.0 * kGravity * std::sin(th) : kGravity * (std::sin(th) - mu * std::cos(th));
    const double exact = 0.5 * accel * T * T;
    char label[64];
    std::snprintf(label, sizeof label, "mu %g (%s): |d/d_exact - 1|", mu,
                  rolls ? "rolling" : "slipping");
    Check ch{"rolling_cylinder_2d", method,   label, k, std::abs(travel / exact - 1.0),
             param(p, "tolerance"), r.seconds};
    ch.note = r.fault;
    out.push_back(ch);
  }
  return out;
}

/// Self-weight column (nu = 0) under gravity applied at once: it oscillates about the static
/// state, so each particle's sigma_yy is averaged over the second half of the run (many
/// periods of the fundamental mode) and compared with sigma_yy = -rho g (H - y).
std::vector<Check> self_weight_column(const json& p, const std::string& method, int k) {
  const double h = param(p, "spacing") / k, H = param(p, "height"), W = param(p, "width");
  const double rho = 1000.0, E = param(p, "youngs_modulus");
  const double y0 = method == "grid" ? 0.0 : param(p, "offset") * h;
  json doc = {{"dimension", 2},
              {"grid",
               {{"min", vec({-4 * h, method == "grid" ? 0.0 : -4 * h})},
                {"max", vec({W + 4 * h, H + 6 * h})},
                {"spacing", h}}},
              {"shape_function", "bspline2"},
              {"scheme", {{"update", "musl"}, {"transfer", "apic"}}},
              {"gravity", vec({0.0, -kGravity})},
              {"materials", json::array({elastic(rho, E, 0.0, "linear_elastic")})},
              {"bodies",
               {{{"material", "m"},
                 {"shape",
                  {{"type", "box"},
                   {"min", vec({0.0, y0})},
                   {"max", vec({W, y0 + H})},
                   {"lattice", "body"}}},
                 {"particles_per_cell", 2}}}},
              {"time", {{"end", param(p, "time")}, {"cfl", 0.4}}}};
  // Free sides: with nu = 0 the exact state is uniaxial stress at any width. The block is wider
  // than tall: a slender column on a frictionless bonded floor (base held level, free to slide)
  // buckles under its own weight (H = 1, W = 0.2 did, in every wall method but the box face).
  doc["walls"] = json::array();
  if (method == "grid") {
    doc["walls"].push_back({{"face", "ymin"}, {"condition", "slip"}});
  } else {
    // A polyline keeps the material on its left: running in +x puts it above. Segments of h:
    // the boundary grid has a cell per segment, and a floor of one long segment would carry the
    // block on its two end nodes only (the block sagged between them).
    json points = json::array();
    const int segments = static_cast<int>(std::lround((W + 2 * h) / h));
    for (int i = 0; i <= segments; ++i) {
      points.push_back(vec({-h + i * (W + 2 * h) / segments, y0}));
    }
    doc["walls"].push_back({{"name", "floor"},
                            {"method", method},
                            {"condition", "slip"},
                            {"surface", {{"type", "polyline"}, {"points", points}}}});
  }
  const double end = param(p, "time");
  std::vector<double> mean_stress, mean_y;
  double averaged = 0.0;
  Run r = run_scene_doc(doc, "self_weight_column", [&](Simulation& s, double t, double dt) {
    if (t < 0.5 * end) return;
    const ParticleFrame f = s.frame(t, 0);
    mean_stress.resize(f.count, 0.0);
    mean_y.resize(f.count, 0.0);
    for (std::size_t i = 0; i < f.count; ++i) {
      mean_stress[i] += f.stress[9 * i + 4] * dt;
      mean_y[i] += f.position[3 * i + 1] * dt;
    }
    averaged += dt;
  });
  // The profile: particles binned in rows of height h, the row's mean sigma_yy against the exact
  // value at the row's mean height; and the particle-by-particle scatter about the exact field.
  double sum = 0.0;
  const int rows = static_cast<int>(std::ceil(H / h));
  std::vector<double> row_stress(rows, 0.0), row_y(rows, 0.0), row_count(rows, 0.0);
  for (std::size_t i = 0; i < mean_stress.size(); ++i) {
    const double y = mean_y[i] / averaged - y0;
    const double exact = -rho * kGravity * (H - y);
    const double e = (mean_stress[i] / averaged - exact) / (rho * kGravity * H);
    sum += e * e;
    const int row = std::clamp(static_cast<int>(std::floor(y / h)), 0, rows - 1);
    row_stress[row] += mean_stress[i] / averaged;
    row_y[row] += y;
    row_count[row] += 1.0;
  }
  // The row at the wall is reported on its own: near a wall MPM's stress carries the boundary
  // error of the kernel (a B-spline cut by the wall), which the interior does not.
  double profile = 0.0, wall_row = 0.0;
  for (int row = 0; row < rows; ++row) {
    if (row_count[row] == 0.0) continue;
    const double y = row_y[row] / row_count[row];
    const double exact = -rho * kGravity * (H - y);
    const double e = std::abs(row_stress[row] / row_count[row] - exact) / (rho * kGravity * H);
    if (row == 0) {
      wall_row = e;
    } else {
      profile = std::max(profile, e);
    }
  }
  const double count = static_cast<double>(std::max<std::size_t>(1, mean_stress.size()));
  const double tol = param(p, "tolerance");
  Check c{"self_weight_column_2d",
          method,
          "rows above the wall row: max |err|/(rho g H)",
          k,
          profile,
          tol,
          r.seconds};
  Check w{"self_weight_column_2d",
          method,
          "row at the wall: |err|/(rho g H)",
          k,
          wall_row,
          tol,
          r.seconds};
  Check d{"self_weight_column_2d",
          method,
          "particles: rms(sigma_yy - exact)/(rho g H)",
          k,
          std::sqrt(sum / count),
          tol,
          r.seconds};
  c.note = w.note = d.note = r.fault;
  return {c, w, d};
}

/// Two elastic disks collide (Sulsky et al. 1994): energy kept, symmetric rebound. Run once per
/// transfer scheme listed in the case ("schemes": label -> scheme object).
std::vector<Check> two_disks(const json& p, const std::string& method, int k) {
  const double h = param(p, "spacing") / k, v = param(p, "speed");
  std::vector<Check> out;
  for (const auto& [listed, scheme] : p.at("schemes").items()) {
    // Under --update (run_scene_doc() replaces the scheme's update) the label says so ("MUSL/APIC"
    // -> "MLS/APIC"); MLS-MPM runs APIC only, so the FLIP disks are left out under it (here,
    // not by run_scene_doc()'s NotApplicable, which would drop the APIC disks with them).
    std::string label = listed;
    if (!g_update.empty()) {
      if (g_update == "mls" && scheme.value("transfer", "apic") != "apic") continue;
      std::string name = g_update;
      for (char& ch : name) ch = static_cast<char>(std::toupper(static_cast<unsigned char>(ch)));
      const std::size_t slash = label.find('/');
      label = name + (slash == std::string::npos ? "" : label.substr(slash));
    }
    json doc = {{"dimension", 2},
                {"grid", {{"min", vec({0.0, 0.0})}, {"max", vec({1.0, 1.0})}, {"spacing", h}}},
                {"shape_function", "bspline2"},
                {"scheme", scheme},
                {"materials", json::array({elastic(1000.0, 1000.0, 0.3, "neo_hookean")})},
                {"bodies",
                 {{{"name", "a"},
                   {"material", "m"},
                   {"shape", {{"type", "disk"}, {"center", vec({0.25, 0.25})}, {"radius", 0.2}}},
                   {"particles_per_cell", 2},
                   {"velocity", vec({v, v})}},
                  {{"name", "b"},
                   {"material", "m"},
                   {"shape", {{"type", "disk"}, {"center", vec({0.75, 0.75})}, {"radius", 0.2}}},
                   {"particles_per_cell", 2},
                   {"velocity", vec({-v, -v})}}}},
                {"time", {{"end", param(p, "time")}, {"cfl", 0.4}}}};
    double e0 = -1.0;
    Run r = run_scene_doc(doc, "two_disks_2d", [&](Simulation& s, double, double) {
      if (e0 < 0.0) e0 = s.energies().total();
    });
    const Energies e = r.sim->energies();
    const ParticleFrame fr = r.sim->frame(0.0, 0);
    Eigen::Vector2d ca = Eigen::Vector2d::Zero(), cb = Eigen::Vector2d::Zero();
    double ma = 0.0, mb = 0.0;
    for (std::size_t i = 0; i < fr.count; ++i) {
      const Eigen::Vector2d x(fr.position[3 * i], fr.position[3 * i + 1]);
      (fr.body[i] == 0 ? ca : cb) += fr.mass[i] * x;
      (fr.body[i] == 0 ? ma : mb) += fr.mass[i];
    }
    ca /= ma;
    cb /= mb;
    Check energy{"two_disks_2d",
                 method,
                 label + ": |E_end/E_0 - 1|",
                 k,
                 std::abs(e.total() / e0 - 1.0),
                 param(p, "energy_tolerance"),
                 r.seconds};
    Check symmetry{"two_disks_2d",
                   method,
                   label + ": |x_a + x_b - (1,1)|/h",
                   k,
                   (ca + cb - Eigen::Vector2d(1.0, 1.0)).norm() / h,
                   param(p, "symmetry_tolerance"),
                   r.seconds};
    energy.note = symmetry.note = r.fault;
    out.push_back(energy);
    out.push_back(symmetry);
  }
  return out;
}

/// A single particle thrown at a slip wall at an angle: its normal velocity must go to zero and
/// its tangential velocity stay.
std::vector<Check> particle_vs_wall(const json& p, const std::string& method, int k) {
  std::vector<Check> out;
  const double h = param(p, "spacing") / k;
  for (const double theta : p.at("angles").get<std::vector<double>>()) {
    const Frame2 f = incline_frame(theta, method);
    const Eigen::Vector2d c = f.origin + 0.5 * f.down + 2.0 * h * f.normal;
    const Eigen::Vector2d v = -1.0 * f.normal + 1.0 * f.down;
    json body = {{"material", "m"},
                 {"shape",
                  {{"type", "box"},
                   {"min", vec({c.x() - 0.25 * h, c.y() - 0.25 * h})},
                   {"max", vec({c.x() + 0.25 * h, c.y() + 0.25 * h})},
                   {"rotation", method == "grid" ? 0.0 : -theta}}},
                 {"particles_per_cell", 1},
                 {"velocity", vec({v.x(), v.y()})}};
    json doc = incline_doc_2d(f, 0.0, method, h, 0.0, 1.5, body, 0.0, param(p, "time"),
                              {{"update", "musl"}, {"transfer", "apic"}});
    doc["gravity"] = vec({0.0, 0.0});
    doc["materials"][0]["youngs_modulus"] = param(p, "youngs_modulus");
    Run r = run_scene_doc(doc, "particle_vs_wall_2d", nullptr);
    const Eigen::Vector3d m = r.sim->momentum();
    const double mass = total_mass(*r.sim);
    const Eigen::Vector2d vend(m.x() / mass, m.y() / mass);
    char label[64];
    std::snprintf(label, sizeof label, "theta %g: |v_n after|/|v_n before|", theta);
    Check ch{"particle_vs_wall_2d", method,   label, k, std::abs(vend.dot(f.normal)),
             param(p, "tolerance"), r.seconds};
    ch.note = r.fault;
    out.push_back(ch);
  }
  return out;
}

}  // namespace

const std::map<std::string, Checker>& checkers() {
  static const std::map<std::string, Checker> map = {
      {"bar_impact_1d", bar_impact},
      {"axial_vibration_1d", axial_vibration},
      {"particle_vs_wall_2d", particle_vs_wall},
      {"incline_block_2d", incline_block_2d},
      {"incline_block_3d", incline_block_3d},
      {"rolling_cylinder_2d", rolling_cylinder_2d},
      {"self_weight_column_2d", self_weight_column},
      {"two_disks_2d", two_disks},
  };
  return map;
}

}  // namespace mpm::tools
