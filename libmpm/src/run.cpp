// The run loop: step, record, report. Nothing here knows the dimension.

#include "mpm/run.hpp"

#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "mpm/output.hpp"
#include "mpm/solver.hpp"

namespace mpm {
namespace {

using Clock = std::chrono::steady_clock;

double seconds_since(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

/// Shortest readable form of a number (6 significant digits): 1.97e-06, not 0.000002.
std::string num(double value) {
  std::ostringstream s;
  s << value;
  return s.str();
}

std::string clock_text(double seconds) {
  const long s = std::lround(std::max(0.0, seconds));
  char text[32];
  std::snprintf(text, sizeof text, "%ld:%02ld:%02ld", s / 3600, (s / 60) % 60, s % 60);
  return text;
}

/// A progress bar with ETA on a terminal; a plain line every 10% otherwise (logs, CI).
class Progress {
 public:
  Progress(double end_time, bool quiet)
      : end_(end_time), quiet_(quiet), tty_(isatty(fileno(stderr)) != 0), start_(Clock::now()) {}

  void update(double t, long step, bool force = false) {
    if (quiet_) return;
    const double fraction = std::min(1.0, t / end_);
    const double elapsed = seconds_since(start_);
    const double eta = fraction > 0 ? elapsed * (1.0 - fraction) / fraction : 0.0;
    if (tty_) {
      if (!force && elapsed - last_draw_ < 0.2) return;
      last_draw_ = elapsed;
      const int width = 30;
      const int filled = static_cast<int>(fraction * width);
      std::fprintf(stderr, "\r[%s%s] %5.1f%%  t=%.4g  step %ld  ETA %s ",
                   std::string(filled, '#').c_str(), std::string(width - filled, '.').c_str(),
                   100.0 * fraction, t, step, clock_text(eta).c_str());
      if (force) std::fputc('\n', stderr);
    } else {
      const int decile = static_cast<int>(fraction * 10.0 + 1e-9);
      if (decile <= last_decile_) return;  // also after the end: the 100% line is printed once
      last_decile_ = decile;
      std::fprintf(stderr, "%5.1f%%  t=%.6g  step %ld  elapsed %s  ETA %s\n", 100.0 * fraction, t,
                   step, clock_text(elapsed).c_str(), clock_text(eta).c_str());
    }
    std::fflush(stderr);
  }

 private:
  double end_;
  bool quiet_, tty_;
  Clock::time_point start_;
  double last_draw_ = -1.0;
  int last_decile_ = -1;
};

const char* const kAxis[] = {"x", "y", "z"};

/// The energy, momentum and wall-force history, one CSV row per history interval. Wall forces
/// are what the material pushes on each wall, averaged over the interval (impulse / time).
class History {
 public:
  History(const std::filesystem::path& file, const Scene& scene, const Simulation& sim)
      : out_(file), dim_(scene.dimension) {
    if (!out_) throw std::runtime_error("cannot write '" + file.string() + "'");
    out_.precision(10);
    out_ << "time,step,dt,kinetic,strain,gravity,total";
    for (int d = 0; d < dim_; ++d) out_ << ",momentum_" << kAxis[d];
    for (const auto& wall : sim.wall_names()) {
      for (int d = 0; d < dim_; ++d) out_ << ",wall_" << wall << "_f" << kAxis[d];
    }
    out_ << '\n';
  }

  void row(double t, long step, double dt, const Simulation& sim, double elapsed) {
    const Energies e = sim.energies();
    const Eigen::Vector3d p = sim.momentum();
    out_ << t << ',' << step << ',' << dt << ',' << e.kinetic << ',' << e.strain << ',' << e.gravity
         << ',' << e.total();
    for (int d = 0; d < dim_; ++d) out_ << ',' << p[d];
    for (const auto& impulse : sim.wall_impulses()) {
      for (int d = 0; d < dim_; ++d) out_ << ',' << (elapsed > 0 ? -impulse[d] / elapsed : 0.0);
    }
    out_ << '\n';
    out_.flush();
  }

 private:
  std::ofstream out_;
  int dim_;
};

void write_json_atomically(const std::filesystem::path& file, const nlohmann::json& doc) {
  const auto tmp = std::filesystem::path(file.string() + ".tmp");
  {
    std::ofstream out(tmp);
    out << doc.dump(2) << '\n';
    if (!out.flush()) throw std::runtime_error("cannot write '" + tmp.string() + "'");
  }
  std::filesystem::rename(tmp, file);
}

nlohmann::json energy_json(const Energies& e) {
  return {
      {"kinetic", e.kinetic}, {"strain", e.strain}, {"gravity", e.gravity}, {"total", e.total()}};
}

}  // namespace

int run_scene(const Scene& scene, const RunOptions& options) {
  namespace fs = std::filesystem;
  const fs::path& out = options.out_dir;
  std::error_code ec;
  if (fs::exists(out / "summary.json", ec) || fs::exists(out / "particles.h5", ec)) {
    if (!options.overwrite) {
      std::cerr << "mpm: " << out.string()
                << ": holds an earlier result; choose another directory or pass --overwrite\n";
      return kExitBadInput;
    }
  }

  std::unique_ptr<Simulation> sim = make_simulation(scene);
  if (sim->particle_count() == 0) {
    std::cerr << "mpm: " << scene.file.string()
              << ": /bodies: no particles were generated (bodies smaller than a sub-cell?)\n";
    return kExitBadInput;
  }

  const auto wall_start = Clock::now();
  std::unique_ptr<ParticleWriter> writer;
  std::unique_ptr<History> history;
  try {
    fs::create_directories(out);
    writer = std::make_unique<ParticleWriter>(out / "particles.h5", out / "particles.xmf");
    history = std::make_unique<History>(out / "history.csv", scene, *sim);
  } catch (const std::exception& e) {
    std::cerr << "mpm: " << out.string() << ": " << e.what() << '\n';
    return kExitIo;
  }

  const double end = scene.end_time;
  const double eps = 1e-12 * end;
  double t = 0.0;
  long step = 0;
  double dt = 0.0;
  double since_history = 0.0;
  double next_output = scene.output_interval;
  double next_history = scene.history_interval;
  double min_dt = std::numeric_limits<double>::infinity(), max_dt = 0.0;
  std::vector<std::string> warnings;
  if (scene.transfer == Transfer::apic && scene.shape != ShapeKind::bspline2) {
    warnings.emplace_back(
        "APIC with the linear or GIMP kernel takes the affine matrix from nearly empty nodes at "
        "full weight and is prone to the cell-crossing instability; prefer bspline2 or FLIP");
  }
  for (const auto& w : warnings) std::cerr << "mpm: warning: " << w << '\n';
  std::optional<std::string> failure;
  Progress progress(end, options.quiet);

  try {
    writer->write(sim->frame(0.0, 0));
    history->row(0.0, 0, 0.0, *sim, 0.0);
    bool last_written = true;
    while (t < end - eps) {
      if (scene.fixed_dt) {
        dt = *scene.fixed_dt;
        // A fixed step must stay below the CFL limit as the material speeds up.
        const double limit = sim->stable_dt(1.0);
        if (dt > limit) {
          failure = "step " + std::to_string(step) + ", t = " + num(t) + ": fixed time step " +
                    num(dt) + " is above the CFL limit h/(c + |v|max) = " + num(limit);
          break;
        }
      } else {
        dt = sim->stable_dt(scene.cfl);
      }
      dt = std::min(dt, end - t);
      sim->step(dt);
      t += dt;
      ++step;
      since_history += dt;
      min_dt = std::min(min_dt, dt);
      max_dt = std::max(max_dt, dt);
      if (sim->fault()) {
        failure = "step " + std::to_string(step) + ", t = " + num(t) + ": " + *sim->fault();
        break;
      }
      if (scene.history_interval == 0.0 || t >= next_history - eps || t >= end - eps) {
        history->row(t, step, dt, *sim, since_history);
        sim->reset_wall_impulses();
        since_history = 0.0;
        while (next_history <= t + eps && scene.history_interval > 0.0) {
          next_history += scene.history_interval;
        }
      }
      last_written = false;
      if (t >= next_output - eps) {
        writer->write(sim->frame(t, step));
        last_written = true;
        while (next_output <= t + eps) next_output += scene.output_interval;
      }
      progress.update(t, step);
    }
    if (!last_written && !failure) writer->write(sim->frame(t, step));
  } catch (const std::exception& e) {
    std::cerr << "\nmpm: " << out.string() << ": " << e.what() << '\n';
    return kExitIo;
  }
  progress.update(t, step, true);

  const double wall_seconds = seconds_since(wall_start);
  nlohmann::json summary = {
      {"scene", scene.file.string()},
      {"name", scene.name},
      {"status", failure ? "failed" : "completed"},
      {"dimension", scene.dimension},
      {"shape_function", std::string(to_string(scene.shape))},
      {"particles", sim->particle_count()},
      {"steps", step},
      {"simulated_time", t},
      {"end_time", end},
      {"dt_min", step > 0 ? min_dt : 0.0},
      {"dt_max", max_dt},
      {"wall_clock_seconds", wall_seconds},
      {"particle_steps_per_second",
       wall_seconds > 0 ? static_cast<double>(sim->particle_count()) * step / wall_seconds : 0.0},
      {"frames_written", writer->frames_written()},
      {"final_energy", energy_json(sim->energies())},
      {"warnings", warnings},
  };
  if (failure) summary["error"] = *failure;
  try {
    write_json_atomically(out / "summary.json", summary);
  } catch (const std::exception& e) {
    std::cerr << "mpm: " << e.what() << '\n';
    return kExitIo;
  }
  if (failure) {
    std::cerr << "mpm: " << scene.file.string() << ": numerical fault at " << *failure
              << "; output up to the previous frame is kept in " << out.string() << '\n';
    return kExitFault;
  }
  return kExitOk;
}

}  // namespace mpm
