#pragma once
// The scenes with exact answers that `mpm verify` checks and `mpm bench` sweeps: one checker per
// case (data/verification/<case>.json holds its parameters) that builds the scene for a wall
// method and refinement factor, runs it and measures the error; and the pieces the benchmarks
// build their own scenes from.

#include <filesystem>
#include <functional>
#include <initializer_list>
#include <map>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <nlohmann/json.hpp>

#include "mpm/solver.hpp"

namespace mpm::tools {

/// One measured check.
struct Check {
  Check(std::string case_name_, std::string method_, std::string measure_, int resolution_,
        double value_, double tolerance_, double seconds_)
      : case_name(std::move(case_name_)),
        method(std::move(method_)),
        measure(std::move(measure_)),
        resolution(resolution_),
        value(value_),
        tolerance(tolerance_),
        seconds(seconds_) {}
  std::string case_name, method, measure;
  int resolution = 1;
  double value = 0.0, tolerance = 0.0, seconds = 0.0;
  bool pass = false;
  std::string note;  ///< e.g. the numerical fault that ended the run
};

/// What a run gives back.
struct Run {
  std::unique_ptr<Simulation> sim;
  Scene scene;
  double seconds = 0.0;
  std::string fault;
  std::int64_t steps = 0;
};

/// Observer called after every step with (simulation, time, step size); returning is all it
/// can do, the run stops at the scene's end time or at a fault.
using Observer = std::function<void(Simulation&, double, double)>;

/// Parses `doc` as a scene (labelled `label` in errors) and runs it to its end time at the
/// scene's CFL number (or for max_steps steps when > 0, if sooner); `start` once before the
/// first step, `observe` after every step. A numerical fault ends the run early and is returned
/// in Run::fault ("t = ...: ..."). Throws SceneError for a scene that does not parse.
Run run_scene_doc(const nlohmann::json& doc, const std::string& label, const Observer& observe,
                  const std::function<void(Simulation&)>& start = nullptr,
                  std::int64_t max_steps = 0);

/// From now on run_scene_doc writes every scene it runs to DIR/<prefix>_<n>.json (empty dir:
/// stop writing). For `mpm verify --scenes`.
void dump_scenes(const std::filesystem::path& dir, const std::string& prefix);
/// Gives every Blending wall (mortar, one-way) of the cases run "multiplier_radius": radius
/// (0: the scenes as the cases write them). Set by verify_command.
void merge_multipliers(double radius);
/// Runs every case under this update scheme ("musl", "usl" or "mls"; empty: the scenes' own).
/// Set by verify_command.
void use_update_scheme(const std::string& update);
/// Thrown by run_scene_doc for a case the update scheme cannot run (MLS-MPM on a kernel other
/// than the quadratic B-spline): verify_command reports the case as not run.
struct NotApplicable : std::runtime_error {
  using std::runtime_error::runtime_error;
};

nlohmann::json vec(std::initializer_list<double> v);
/// A wall condition: "friction" with mu > 0, else "slip".
nlohmann::json contact(double mu, bool separable);
/// An elastic material named "m"; poisson < 0 leaves the ratio out (1D).
nlohmann::json elastic(double density, double youngs, double poisson, const std::string& model);
double total_mass(const Simulation& s);

/// A 2D incline: a wall point, the downhill direction and the normal into the material. "grid"
/// keeps the wall on the box floor (and the scenes turn gravity); others turn it by theta and
/// move it off the nodes.
struct Frame2 {
  Eigen::Vector2d origin, down, normal;
};
Frame2 incline_frame(double theta_deg, const std::string& method);

/// The 2D scene skeleton: a wall along `f` from u0 to u1 (downhill) for `method`, the grid box
/// around it, `body`, gravity at angle theta to the wall's normal, friction mu (separable).
nlohmann::json incline_doc_2d(const Frame2& f, double theta_deg, const std::string& method,
                              double h, double u0, double u1, const nlohmann::json& body, double mu,
                              double end, const nlohmann::json& scheme);

/// A case's checker: (the "params" of its file, wall method, refinement factor K) -> checks.
using Checker = std::vector<Check> (*)(const nlohmann::json&, const std::string&, int);
/// Every case by name.
const std::map<std::string, Checker>& checkers();

}  // namespace mpm::tools
