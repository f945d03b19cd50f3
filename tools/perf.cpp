// `mpm bench perf`: issue 9's step targets measured in one run, every ratio between timings of
// rounds interleaved with each other (this machine is shared and its speed drifts by 10% within
// minutes: a number from another run is no reference). The scenes are
// bench/bench_step.cpp's (bench/perf_scenes.hpp); the yardstick
// (../shared/tools/yardstick/run.sh) is not part of the project: its script is run once per
// round of the standard block (--yardstick-script), or its throughput, measured in the same
// session, is passed in (--yardstick), to print the throughput ratio.

#include <tbb/global_control.h>
#include <tbb/info.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <optional>
#include <regex>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "mpm/run.hpp"
#include "mpm/solver.hpp"
#include "perf_scenes.hpp"
#include "process.hpp"

namespace mpm::tools {
namespace {

using json = nlohmann::json;

/// The median of `values` (the upper one of an even count), which must not be empty.
double median_of(std::vector<double> values) {
  std::sort(values.begin(), values.end());
  return values[values.size() / 2];
}

/// One timed scene: milliseconds per step, per phase, and the couplings' work per step.
struct Timing {
  std::size_t particles = 0;
  double ms_per_step = 0.0;         ///< the median of the rounds
  double bytes_per_particle = 0.0;  ///< heap grown while the solver was made and stepped once
  PhaseTimes phases;                ///< milliseconds per step, over all rounds
  /// The dual-grid walls' work per timed step (perf::per_step(): parts in milliseconds).
  perf::SolveCount coupling;
  std::string fault;

  [[nodiscard]] double rate() const {  // particle-steps per second
    return static_cast<double>(particles) / (1e-3 * ms_per_step);
  }
};

/// A scene's solver, stepped `settle` times (the CFL step at 0.3, as bench_step), then timed in
/// rounds of `steps` steps (on at most `threads` threads, 0: all) that the caller interleaves
/// with the other scenes' rounds, so that a ratio of two scenes' medians is not a drift of the
/// machine's speed between them.
class Timed {
 public:
  Timed(const Scene& scene, int settle, int threads) : threads_(threads) {
    const double heap = perf::heap_bytes();
    solver_ = std::make_unique<Solver<3>>(scene);
    dt_ = solver_->stable_dt(0.3);
    auto limit = limit_threads();
    solver_->step(dt_);
    t_.particles = solver_->particle_count();
    t_.bytes_per_particle =
        (perf::heap_bytes() - heap + static_cast<double>(solver_->grid.committed_bytes())) /
        static_cast<double>(t_.particles);
    for (int k = 1; k < settle && !solver_->fault(); ++k) solver_->step(dt_);
    solves0_ = perf::solve_count(*solver_);
    before_ = solver_->phase_times();
  }

  void round(int steps) {
    if (solver_->fault()) return;
    auto limit = limit_threads();
    const auto start = std::chrono::steady_clock::now();
    for (int k = 0; k < steps && !solver_->fault(); ++k) solver_->step(dt_);
    rounds_.push_back(
        1e3 * std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() /
        steps);
    steps_ += steps;
  }

  /// The median round and the phases and work per step over all rounds.
  Timing result() {
    if (solver_->fault()) t_.fault = *solver_->fault();
    if (rounds_.empty()) return t_;
    t_.ms_per_step = median_of(rounds_);
    t_.phases = perf::ms_per_step(solver_->phase_times(), before_, steps_);
    t_.coupling = perf::per_step(perf::solve_count(*solver_), solves0_, steps_);
    return t_;
  }

 private:
  std::unique_ptr<tbb::global_control> limit_threads() const {
    if (threads_ <= 0) return nullptr;
    return std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism,
                                                 static_cast<std::size_t>(threads_));
  }

  int threads_;
  std::unique_ptr<Solver<3>> solver_;
  double dt_ = 0.0;
  Timing t_;
  PhaseTimes before_;
  perf::SolveCount solves0_;  ///< the couplings' work before the timed rounds
  double steps_ = 0.0;
  std::vector<double> rounds_;
};

/// Times `scenes` in `rounds` interleaved rounds of `steps` steps each; `before_round(r)`, if
/// given, runs before each round r.
std::vector<Timing> time_together(std::vector<std::unique_ptr<Timed>>& scenes, int rounds,
                                  int steps, const std::function<void(int)>& before_round = {}) {
  for (int r = 0; r < rounds; ++r) {
    if (before_round) before_round(r);
    for (auto& s : scenes) s->round(steps);
  }
  std::vector<Timing> timings;
  for (auto& s : scenes) timings.push_back(s->result());
  return timings;
}

/// The yardstick (../shared/tools/yardstick/run.sh, a stripped MLS-MPM step that is not part of
/// the project) run as a program, once per round of the standard block: the throughput ratio is
/// then of medians over interleaved rounds, as every other ratio here, instead of against a
/// rate measured minutes away (the machine's speed drifts by 10% within minutes). The script
/// prints a line "threads T particles N steps S time X s -> R M particle-steps/s" per thread
/// count; the rate on this run's thread count is kept.
class Yardstick {
 public:
  Yardstick(const std::filesystem::path& script, int threads)
      : script_(std::filesystem::absolute(script).lexically_normal()), threads_(threads) {}

  /// Runs the script once; false, with error() saying why in one line, when it cannot be run,
  /// fails, or prints no rate for this run's thread count.
  bool round() {
    std::error_code ec;
    if (!std::filesystem::is_regular_file(script_, ec)) return fail("is not a file");
    if (::access(script_.c_str(), X_OK) != 0) return fail("is not executable");
    const ProcessResult run = run_process({script_.string()}, true);
    if (!run.error.empty()) return fail("cannot be started (" + run.error + ")");
    if (run.exit_code != 0) {
      return fail(run.exit_code >= 0 ? "exited with status " + std::to_string(run.exit_code)
                                     : std::string("was killed"));
    }
    static const std::regex line(R"(threads (\d+) .*-> ([0-9.eE+-]+) M particle-steps/s)");
    std::istringstream lines(run.output);
    for (std::string text; std::getline(lines, text);) {
      std::smatch m;
      if (!std::regex_search(text, m, line) || m[1].str() != std::to_string(threads_)) continue;
      const double rate = std::strtod(m[2].str().c_str(), nullptr);
      if (!(rate > 0.0) || !std::isfinite(rate)) break;
      rates_.push_back(rate);
      return true;
    }
    return fail("printed no rate for " + std::to_string(threads_) + " threads (a line \"threads " +
                std::to_string(threads_) + " ... -> R M particle-steps/s\")");
  }

  [[nodiscard]] double median() const { return median_of(rates_); }
  /// True once a run has failed (error() says why); later rounds then do not run it.
  [[nodiscard]] bool failed() const { return !error_.empty(); }
  [[nodiscard]] const std::vector<double>& rates() const { return rates_; }
  [[nodiscard]] const std::string& error() const { return error_; }
  [[nodiscard]] const std::filesystem::path& script() const { return script_; }

 private:
  bool fail(const std::string& why) {
    error_ = "--yardstick-script " + script_.string() + ": " + why;
    return false;
  }

  std::filesystem::path script_;
  int threads_;
  std::vector<double> rates_;
  std::string error_;
};

json to_json(const Timing& t) {
  json j = {{"particles", t.particles},
            {"ms_per_step", t.ms_per_step},
            {"particle_steps_per_second", t.rate()},
            {"bytes_per_particle", t.bytes_per_particle},
            {"ms_phases",
             {{"locate", t.phases.locate},
              {"particles_to_grid", t.phases.particles_to_grid},
              {"grid_update", t.phases.grid_update},
              {"walls", t.phases.walls},
              {"coupling", t.phases.coupling},
              {"grid_to_particles", t.phases.grid_to_particles},
              {"stress", t.phases.stress},
              {"advect", t.phases.advect}}},
            {"factorizations_per_step", t.coupling.factorizations},
            {"refinement_passes_per_step", t.coupling.refinements},
            {"ms_coupling_parts",
             {{"assembly", t.coupling.assembly},
              {"factorizing", t.coupling.factorizing},
              {"solves", t.coupling.solves}}}};
  if (!t.fault.empty()) j["fault"] = t.fault;
  return j;
}

/// The least-squares slope of log(time per step) against log(particles).
double fitted_exponent(const std::vector<Timing>& runs) {
  double sx = 0.0, sy = 0.0, sxx = 0.0, sxy = 0.0;
  for (const Timing& t : runs) {
    const double x = std::log(static_cast<double>(t.particles)), y = std::log(t.ms_per_step);
    sx += x;
    sy += y;
    sxx += x * x;
    sxy += x * y;
  }
  const auto n = static_cast<double>(runs.size());
  return (n * sxy - sx * sy) / (n * sxx - sx * sx);
}

void print_row(const std::string& name, const Timing& t, const std::string& note) {
  std::printf("  %-40s %9zu %10.2f %9.2f  %s\n", name.c_str(), t.particles, t.ms_per_step,
              1e-6 * t.rate(), note.c_str());
}

std::string fixed(double value, int digits = 2) {
  char text[32];
  std::snprintf(text, sizeof text, "%.*f", digits, value);
  return text;
}

// perf_command() without its report of what its scenes throw.
int timed_perf(const PerfArgs& args) {
  const int cells = args.smoke ? 6 : args.cells;
  const int steps = args.smoke ? 2 : args.steps;
  const int rounds = args.rounds.value_or(args.smoke ? 1 : 5);
  const int settle = args.settle;
  const int threads = static_cast<int>(
      tbb::global_control::active_value(tbb::global_control::max_allowed_parallelism));
  // The yardstick's first round, before anything is written: a script that cannot be run fails
  // here, with the JSON file as it was.
  std::optional<Yardstick> yardstick;
  if (!args.yardstick_script.empty()) {
    yardstick.emplace(args.yardstick_script, threads);
    if (!yardstick->round()) {
      std::cerr << "mpm bench perf: " << yardstick->error() << "\n";
      return kExitBadInput;
    }
  }
  // The JSON file is opened next: a path that cannot be written fails before the minute of
  // timing, not after it.
  std::ofstream out;
  if (!args.json_file.empty()) {
    out.open(args.json_file);
    if (!out) {
      std::cerr << "mpm bench perf: cannot write " << args.json_file.string() << "\n";
      return kExitIo;
    }
  }
  json report = {{"cells", cells},
                 {"steps", steps},
                 {"rounds", rounds},
                 {"settle", settle},
                 {"threads", threads}};
  bool faulted = false;
  auto note_fault = [&](const std::string& name, const Timing& t) {
    if (t.fault.empty()) return;
    faulted = true;
    std::cerr << "mpm bench perf: " << name << ": numerical fault: " << t.fault << "\n";
  };
  std::printf(
      "mpm bench perf: %d^3-cell block, %d rounds of %d timed steps each (median) after %d, %d "
      "threads\n",
      cells, rounds, steps, settle, threads);
  std::printf("  %-40s %9s %10s %9s\n", "step", "particles", "ms/step", "M p-s/s");

  // The standard step, MUSL (the default), USL (one transfer each way, as the yardstick) and
  // MLS-MPM (USL's order with the yardstick's force and gradient), on all threads and on one, in
  // interleaved rounds.
  const char* const updates[] = {"musl", "usl", "mls"};
  std::vector<std::unique_ptr<Timed>> standard;
  for (const char* update : updates) {
    const Scene scene = perf::block_scene(cells, update);
    standard.push_back(std::make_unique<Timed>(scene, settle, 0));
    standard.push_back(std::make_unique<Timed>(scene, settle, 1));
  }
  // The yardstick's later rounds run before the standard block's (its first ran above).
  const std::vector<Timing> blocks = time_together(standard, rounds, steps, [&](int r) {
    if (r > 0 && yardstick && !yardstick->failed()) yardstick->round();
  });
  standard.clear();  // the floors and the scaling runs need the memory
  double yardstick_rate = args.yardstick;
  if (yardstick) {
    json entry = {{"script", yardstick->script().string()},
                  {"threads", threads},
                  {"rates", yardstick->rates()}};
    if (!yardstick->failed()) {
      yardstick_rate = yardstick->median();
      entry["median"] = yardstick_rate;
      const auto [lo, hi] =
          std::minmax_element(yardstick->rates().begin(), yardstick->rates().end());
      std::printf("  %-40s %9s %10s %9.2f  median of %zu runs (%s-%s), one before each round\n",
                  "yardstick (its script)", "", "", yardstick_rate, yardstick->rates().size(),
                  fixed(*lo).c_str(), fixed(*hi).c_str());
    } else {
      faulted = true;
      entry["error"] = yardstick->error();
      std::cerr << "mpm bench perf: " << yardstick->error() << " (no throughput ratio)\n";
    }
    report["yardstick"] = entry;
  }
  for (int u = 0; u < 3; ++u) {
    const std::string update = updates[u];
    const Timing& all = blocks[static_cast<std::size_t>(2 * u)];
    const Timing& one = blocks[static_cast<std::size_t>(2 * u + 1)];
    note_fault(update, all);
    note_fault(update, one);
    const double speedup = one.ms_per_step / all.ms_per_step;
    std::string note = "1 -> " + std::to_string(threads) + " threads: " + fixed(speedup);
    json entry = {
        {"all_threads", to_json(all)}, {"one_thread", to_json(one)}, {"parallel_speedup", speedup}};
    if (yardstick_rate > 0.0) {
      const double ratio = 1e-6 * all.rate() / yardstick_rate;
      note += ", " + fixed(ratio) + " x yardstick";
      entry["yardstick_ratio"] = ratio;
    }
    print_row("standard " + update, all, note);
    print_row("standard " + update + ", 1 thread", one, "");
    report["standard_" + update] = entry;
  }

  // The floor: 10% of the particles in the wall's layer, each wall method against the standard
  // box wall, in interleaved rounds; under MUSL (the default) and again under MLS-MPM, whose
  // couplings skip the remap's solve but whose standard step is cheaper too.
  const char* methods[] = {"standard wall", "mortar", "one-way", "enhanced",
                           "mortar, merged multipliers"};
  const char* keys[] = {"standard", "mortar", "one_way", "enhanced", "mortar_merged"};
  for (const char* update : {"musl", "mls"}) {
    const bool musl = std::string(update) == "musl";
    std::vector<std::unique_ptr<Timed>> floors;
    for (int m = 0; m < 5; ++m) {
      floors.push_back(std::make_unique<Timed>(perf::floor_scene(cells, m, update), settle, 0));
    }
    const std::vector<Timing> floor_times = time_together(floors, rounds, steps);
    floors.clear();  // likewise
    const std::string label = musl ? "floor, " : "floor (mls), ";
    json floor = json::object();
    for (int m = 0; m < 5; ++m) {
      const Timing& t = floor_times[static_cast<std::size_t>(m)];
      note_fault(label + methods[m], t);
      json entry = to_json(t);
      std::string note;
      if (m > 0) {
        const double ratio = t.ms_per_step / floor_times[0].ms_per_step;
        entry["ratio_to_standard"] = ratio;
        note = fixed(ratio) + " x standard (coupling " + fixed(t.phases.coupling) +
               " ms; assembly " + fixed(t.coupling.assembly) + ", factorizing " +
               fixed(t.coupling.factorizing) + ", solves " + fixed(t.coupling.solves) + ")";
      }
      print_row(label + methods[m], t, note);
      floor[keys[m]] = entry;
    }
    report[musl ? "floor" : "floor_mls"] = floor;
  }

  // Scaling: the MUSL block from about 10^4 to 10^6 particles (8 per cell), one size at a time.
  const std::vector<int> sizes =
      args.smoke ? std::vector<int>{4, 6} : std::vector<int>{11, 16, 24, 32, 50};
  std::vector<Timing> scaling;
  json scaling_runs = json::array();
  for (const int n : sizes) {
    std::vector<std::unique_ptr<Timed>> one;
    one.push_back(std::make_unique<Timed>(perf::block_scene(n), 1, 0));
    const Timing t = time_together(one, rounds, std::max(1, steps / 4)).front();
    note_fault("scaling", t);
    scaling.push_back(t);
    scaling_runs.push_back(
        {{"cells", n}, {"particles", t.particles}, {"ms_per_step", t.ms_per_step}});
    print_row("scaling, " + std::to_string(n) + "^3 cells", t, "");
  }
  const double exponent = fitted_exponent(scaling);
  std::printf("  time per step ~ particles^%.3f (least squares over %zu sizes)\n", exponent,
              scaling.size());
  std::printf("  memory: %.0f bytes per particle (standard MUSL, grid included)\n",
              blocks[0].bytes_per_particle);
  report["scaling"] = {{"runs", scaling_runs}, {"exponent", exponent}};

  if (!args.json_file.empty()) {
    out << report.dump(2) << "\n";
    out.close();
    if (!out) {
      std::cerr << "mpm bench perf: cannot write " << args.json_file.string() << "\n";
      return kExitIo;
    }
  }
  return faulted ? 1 : kExitOk;
}

}  // namespace

int perf_command(const PerfArgs& args) {
  try {
    return timed_perf(args);
  } catch (const std::exception& e) {  // its scenes' files (the floor's mesh) unreadable
    std::cerr << "mpm bench perf: " << e.what() << "\n";
    return kExitIo;
  }
}

}  // namespace mpm::tools
