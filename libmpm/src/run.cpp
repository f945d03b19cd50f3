// The run loop: step, record, report. Nothing here knows the dimension.

#include "mpm/run.hpp"

#include <unistd.h>

#include <algorithm>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <numbers>
#include <optional>
#include <sstream>

#include <nlohmann/json.hpp>

#include "mpm/boundary_package.hpp"
#include "mpm/checkpoint.hpp"
#include "mpm/output.hpp"
#include "mpm/solver.hpp"
#include "sync_file.hpp"

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
  /// A new file, or (append_at > 0) an earlier run's file cut back to its first append_at
  /// bytes, the rows up to its checkpoint.
  History(const std::filesystem::path& file, const Scene& scene, const Simulation& sim,
          std::uintmax_t append_at = 0)
      : file_(file), dim_(scene.dimension) {
    if (append_at > 0) {  // run_scene() has checked the length (check_resumable())
      std::error_code error;
      std::filesystem::resize_file(file, append_at, error);
      if (error) throw std::runtime_error("cannot write '" + file.string() + "'");
      out_.open(file, std::ios::app);
    } else {
      out_.open(file, std::ios::trunc);
    }
    if (!out_) throw std::runtime_error("cannot write '" + file.string() + "'");
    out_.precision(10);
    if (append_at > 0) return;
    out_ << "time,step,dt,kinetic,strain,gravity,total";
    for (int d = 0; d < dim_; ++d) out_ << ",momentum_" << kAxis[d];
    for (const auto& wall : sim.wall_names()) {
      for (int d = 0; d < dim_; ++d) out_ << ",wall_" << wall << "_f" << kAxis[d];
    }
    out_ << '\n';
  }

  /// Throws unless `file` holds at least the `append_at` bytes a checkpoint counts. Shorter (a
  /// power cut took its tail), resize_file would pad it with zero bytes: rows that look written
  /// and are not. Checked before a resume changes any file.
  static void check_resumable(const std::filesystem::path& file, std::uintmax_t append_at) {
    std::error_code error;
    const std::uintmax_t size = std::filesystem::file_size(file, error);
    if (error || size < append_at) {
      throw std::runtime_error("'" + file.string() + "' holds " +
                               (error ? std::string("no") : std::to_string(size)) +
                               " bytes, fewer than the " + std::to_string(append_at) +
                               " its checkpoint counts; run the scene afresh with --overwrite");
    }
  }

  /// Writes a row; returns the force on each wall (what the CSV holds), for the peaks.
  std::vector<Eigen::Vector3d> row(double t, long step, double dt, const Simulation& sim,
                                   double elapsed, const Energies& e) {
    const Eigen::Vector3d p = sim.momentum();
    out_ << t << ',' << step << ',' << dt << ',' << e.kinetic << ',' << e.strain << ',' << e.gravity
         << ',' << e.total();
    for (int d = 0; d < dim_; ++d) out_ << ',' << p[d];
    std::vector<Eigen::Vector3d> forces;
    for (const auto& impulse : sim.wall_impulses()) {
      forces.push_back(elapsed > 0 ? Eigen::Vector3d(-impulse / elapsed) : Eigen::Vector3d::Zero());
      for (int d = 0; d < dim_; ++d) out_ << ',' << forces.back()[d];
    }
    out_ << '\n';
    out_.flush();
    return forces;
  }

  /// Bytes written so far (flushed and on the disk, before the checkpoint that counts them):
  /// where a resumed run cuts the file back to.
  std::uintmax_t bytes() {
    out_.flush();
    if (!out_ || !detail::sync_to_disk(file_)) {
      throw std::runtime_error("cannot write '" + file_.string() + "'");
    }
    return std::filesystem::file_size(file_);
  }

 private:
  std::filesystem::path file_;
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

/// The largest force (by magnitude) on each wall over the history rows, and when; and the
/// impulse (the time integral of the force: the momentum the wall took from the material).
/// The peak of a short average depends on how the particles sample the flow's front (a shift of
/// a fraction of a cell moves it by tens of percent at a coarse spacing, docs/debris.md); the
/// impulse of an impact is fixed by the momentum the flow brings, and is what such a shift or a
/// rotation of the scene must not change.
struct ForcePeaks {
  std::vector<Eigen::Vector3d> force, impulse;
  std::vector<double> time;
  /// `forces`: the history row's; `given`: the impulses the walls gave the material since the
  /// last row (the wall takes the opposite).
  void add(double t, const std::vector<Eigen::Vector3d>& forces,
           const std::vector<Eigen::Vector3d>& given) {
    force.resize(forces.size(), Eigen::Vector3d::Zero());
    impulse.resize(forces.size(), Eigen::Vector3d::Zero());
    time.resize(forces.size(), 0.0);
    for (std::size_t i = 0; i < forces.size(); ++i) {
      impulse[i] -= given[i];
      if (forces[i].norm() > force[i].norm()) {
        force[i] = forces[i];
        time[i] = t;
      }
    }
  }
};

/// 3-vectors as one list of numbers (a checkpoint's), and back.
std::vector<double> flatten(const std::vector<Eigen::Vector3d>& vectors) {
  std::vector<double> out;
  for (const auto& v : vectors) out.insert(out.end(), v.data(), v.data() + 3);
  return out;
}
std::vector<Eigen::Vector3d> unflatten(const std::vector<double>& numbers) {
  std::vector<Eigen::Vector3d> out;
  for (std::size_t i = 0; i + 2 < numbers.size(); i += 3) {
    out.emplace_back(numbers[i], numbers[i + 1], numbers[i + 2]);
  }
  return out;
}

Eigen::Vector3d frame_point(const ParticleFrame& f, std::size_t p) {
  return {f.position[3 * p], f.position[3 * p + 1], f.position[3 * p + 2]};
}

/// The deposit's depth at each particle of `last`: the placement volume (the volume in `first`,
/// at J = 1) of the particles within horizontal distance `radius` of it, over the disc's area
/// (3D: pi r^2; 2D, plane strain: the segment's length 2 r, volumes being areas). `down` is the
/// unit gravity direction; only the first `count` particles (present in both frames) take part.
/// The placement volume, not the current one, so a loosened spray (its J grows, capped) does not
/// read as a deep deposit. A depth below the particles' own layer (half a cell at 2 particles
/// per cell) is not resolved: one stray layer reads as that deep.
std::vector<double> deposit_depth(const ParticleFrame& first, const ParticleFrame& last,
                                  std::size_t count, int dimension, const Eigen::Vector3d& down,
                                  double radius) {
  // Horizontal coordinates: 2D, the in-plane direction across gravity; 3D, two across it.
  Eigen::Vector3d e1, e2 = Eigen::Vector3d::Zero();
  if (dimension == 2) {
    e1 = Eigen::Vector3d(-down.y(), down.x(), 0.0);
  } else {
    Eigen::Index least = 0;
    down.cwiseAbs().minCoeff(&least);
    e1 = down.cross(Eigen::Vector3d::Unit(least)).normalized();
    e2 = down.cross(e1);
  }
  struct Point {
    long bx, by;  // bin of side `radius`
    double u, v;
    std::size_t p;
  };
  std::vector<Point> points(count);
  for (std::size_t p = 0; p < count; ++p) {
    const Eigen::Vector3d x = frame_point(last, p);
    const double u = x.dot(e1), v = x.dot(e2);
    points[p] = {std::lround(std::floor(u / radius)), std::lround(std::floor(v / radius)), u, v, p};
  }
  std::sort(points.begin(), points.end(), [](const Point& a, const Point& b) {
    return a.bx != b.bx ? a.bx < b.bx : a.by < b.by;
  });
  const double area = dimension == 2 ? 2.0 * radius : std::numbers::pi * radius * radius;
  std::vector<double> depth(count, 0.0);
  for (const Point& a : points) {
    double sum = 0.0;
    for (long bx = a.bx - 1; bx <= a.bx + 1; ++bx) {
      // The bins (bx, a.by - 1 .. a.by + 1) are one run of the sorted list.
      auto lo = std::lower_bound(points.begin(), points.end(), std::pair{bx, a.by - 1},
                                 [](const Point& q, const std::pair<long, long>& key) {
                                   return q.bx != key.first ? q.bx < key.first : q.by < key.second;
                                 });
      for (; lo != points.end() && lo->bx == bx && lo->by <= a.by + 1; ++lo) {
        const double du = lo->u - a.u, dv = lo->v - a.v;
        if (du * du + dv * dv <= radius * radius) sum += first.volume[lo->p];
      }
    }
    depth[a.p] = sum / area;
  }
  return depth;
}

/// What a hazard engineer reads first: how far the flow ran, where its mass went, whether mass
/// was kept, and what each retaining wall holds back. Horizontal means perpendicular to gravity
/// (all directions when there is none), so the numbers do not depend on how the scene is turned.
///
/// `runout_distance` is the furthest any particle travelled: a single particle's, which a finer
/// spacing pushes further (a thinner tail of the deposit can form; docs/validation.md, column
/// collapse). `runout_at_depth` gives, for each of the scene's `runout_depths`, the furthest any
/// particle travelled among those where the deposit is at least that deep (deposit_depth() over
/// a radius of 2 h), which converges as the spacing shrinks when the depth is one the coarsest
/// spacing resolves (at least half a cell).
nlohmann::json flow_summary(const Scene& scene, const ParticleFrame& first,
                            const ParticleFrame& last) {
  Eigen::Vector3d down = Eigen::Vector3d::Zero();
  down.head(scene.dimension) = scene.gravity;
  if (down.norm() > 0.0) down.normalize();
  const auto horizontal = [&](const Eigen::Vector3d& v) -> Eigen::Vector3d {
    return v - v.dot(down) * down;
  };
  double m0 = 0.0, m1 = 0.0, runout = 0.0, volume = 0.0;
  Eigen::Vector3d c0 = Eigen::Vector3d::Zero(), c1 = Eigen::Vector3d::Zero();
  const std::size_t n = std::min(first.count, last.count);
  for (std::size_t p = 0; p < first.count; ++p) {
    m0 += first.mass[p];
    c0 += first.mass[p] * frame_point(first, p);
  }
  for (std::size_t p = 0; p < last.count; ++p) {
    m1 += last.mass[p];
    c1 += last.mass[p] * frame_point(last, p);
    volume += last.volume[p];
  }
  std::vector<double> travel(n);  // each particle's horizontal travel
  for (std::size_t p = 0; p < n; ++p) {
    travel[p] = horizontal(frame_point(last, p) - frame_point(first, p)).norm();
    runout = std::max(runout, travel[p]);
  }
  if (m0 > 0.0) c0 /= m0;
  if (m1 > 0.0) c1 /= m1;
  nlohmann::json at_depth = nlohmann::json::array();
  if (scene.dimension > 1 && down.norm() > 0.0 && n > 0) {
    const double radius = 2.0 * scene.spacing;
    const std::vector<double> depth = deposit_depth(first, last, n, scene.dimension, down, radius);
    std::vector<double> depths = scene.runout_depths;
    if (depths.empty()) depths.push_back(scene.spacing * scene.resolution);
    for (const double d : depths) {
      double reach = 0.0;
      for (std::size_t p = 0; p < n; ++p) {
        if (depth[p] >= d) reach = std::max(reach, travel[p]);
      }
      at_depth.push_back({{"depth", d}, {"distance", reach}, {"radius", radius}});
    }
  }
  nlohmann::json out = {
      {"mass_initial", m0},
      {"mass_final", m1},
      {"mass_relative_change", m0 > 0.0 ? (m1 - m0) / m0 : 0.0},
      {"runout_distance", runout},
      {"runout_at_depth", at_depth},
      {"centroid_travel", horizontal(c1 - c0).norm()},
      {"final_volume", volume},
  };
  for (const Scene::RetainingWall& retaining : scene.retaining_walls) {
    // The centre of the wall's Gamma facets, or of its part's.
    const auto& layer = scene.dual_walls[static_cast<std::size_t>(retaining.wall)].package->layer;
    Eigen::Vector3d centre = Eigen::Vector3d::Zero();
    double count = 0.0;
    for (Eigen::Index f = 0; f < layer.wall_facets.rows(); ++f) {
      if (retaining.part >= 0 && layer.wall_facet_part[f] != retaining.part) continue;
      for (Eigen::Index k = 0; k < layer.wall_facets.cols(); ++k) {
        centre.head(layer.nodes.cols()) += layer.nodes.row(layer.wall_facets(f, k)).transpose();
        count += 1.0;
      }
    }
    if (count > 0.0) centre /= count;
    Eigen::Vector3d facing = horizontal(c0 - centre);
    if (facing.norm() > 0.0) facing.normalize();
    double retained = 0.0, passed = 0.0;
    for (std::size_t p = 0; p < last.count; ++p) {
      ((frame_point(last, p) - centre).dot(facing) > 0.0 ? retained : passed) += last.volume[p];
    }
    out["retaining_walls"][retaining.name] = {{"volume_on_source_side", retained},
                                              {"volume_past_wall", passed}};
  }
  return out;
}

/// Identifies the scene a checkpoint belongs to: a hash of the scene file's text.
std::string scene_digest(const Scene& scene) {
  std::ifstream in(scene.file, std::ios::binary);
  std::ostringstream text;
  text << in.rdbuf();
  std::ostringstream hex;
  hex << std::hex << std::hash<std::string>{}(text.str());
  return hex.str();
}

/// Runaway energy: the total (kinetic + strain + gravitational) energy of a run without other
/// body forces can only fall, up to round-off and the small gains of the transfers. The run is
/// stopped when it has risen above its start by more than the largest kinetic + strain energy it
/// has held and more than the material's weight times one cell (all of it jumping by h): a gain
/// no correct run comes near, which a blow-up passes before a value turns non-finite (in the
/// test, an unstable step, two steps before the CFL check trips on the speed).
class EnergyGuard {
 public:
  EnergyGuard(const Scene& scene, const ParticleFrame& first) {
    for (const BodySpec& body : scene.bodies) {
      if (body.body_force.size() > 0 && body.body_force.norm() > 0.0) active_ = false;
    }
    double mass = 0.0;
    for (const double m : first.mass) mass += m;
    floor_ = mass * scene.gravity.norm() * scene.spacing;
  }

  void start(double total, double mechanical) {
    start_ = total;
    peak_ = mechanical;
  }

  /// The runaway description, or nothing; `e` is this history row's energies.
  std::optional<std::string> check(const Energies& e, const Simulation& sim, const Scene& scene,
                                   double t, long step) {
    const double gain = e.total() - start_;
    const double limit = std::max(peak_, floor_);
    peak_ = std::max(peak_, e.kinetic + e.strain);
    if (!active_ || !(gain > limit)) return std::nullopt;
    // Name the particle moving fastest, where a blow-up shows first.
    const ParticleFrame f = sim.frame(t, step);
    std::size_t fastest = 0;
    double speed = -1.0;
    for (std::size_t p = 0; p < f.count; ++p) {
      const double v = std::hypot(f.velocity[3 * p], f.velocity[3 * p + 1], f.velocity[3 * p + 2]);
      if (v > speed) {
        speed = v;
        fastest = p;
      }
    }
    std::ostringstream text;
    text << "runaway energy: the total energy rose by " << gain
         << " J above its start, more than the largest kinetic + strain energy held (or the "
            "weight times one cell), "
         << limit << " J; fastest particle " << fastest << " (material \""
         << scene.materials[static_cast<std::size_t>(f.material[fastest])].name << "\", body \""
         << scene.bodies[static_cast<std::size_t>(f.body[fastest])].name << "\") at " << speed
         << " m/s";
    return text.str();
  }

  [[nodiscard]] std::vector<double> state() const { return {start_, peak_}; }
  void restore(const std::vector<double>& state) {
    start_ = state[0];
    peak_ = state[1];
  }

 private:
  bool active_ = true;
  double floor_ = 0.0;
  double start_ = 0.0;
  double peak_ = 0.0;
};

nlohmann::json energy_json(const Energies& e) {
  return {
      {"kinetic", e.kinetic}, {"strain", e.strain}, {"gravity", e.gravity}, {"total", e.total()}};
}

// Where the steps' time went (this process only: a resumed run counts from its resume),
// and the output's (history rows, particle frames, checkpoints).
nlohmann::json phase_json(const PhaseTimes& p, double output) {
  return {{"locate", p.locate},           {"particles_to_grid", p.particles_to_grid},
          {"grid_update", p.grid_update}, {"walls", p.walls},
          {"coupling", p.coupling},       {"grid_to_particles", p.grid_to_particles},
          {"stress", p.stress},           {"advect", p.advect},
          {"steps_total", p.total()},     {"output", output}};
}

}  // namespace

CheckpointOrigin checkpoint_origin(const std::filesystem::path& out_dir) {
  const Checkpoint c = read_checkpoint(out_dir / "checkpoint.h5", true);
  CheckpointOrigin origin{c.text("run.scene"), 1};
  const auto it = c.texts.find("run.resolution");  // absent in checkpoints before the option
  if (it == c.texts.end()) return origin;
  int& k = origin.resolution;
  const auto [end, error] =
      std::from_chars(it->second.data(), it->second.data() + it->second.size(), k);
  if (error != std::errc() || end != it->second.data() + it->second.size() || k < 1) {
    throw std::runtime_error((out_dir / "checkpoint.h5").string() + ": run.resolution '" +
                             it->second + "' is not a positive integer");
  }
  return origin;
}

int run_scene(const Scene& scene, const RunOptions& options) {
  namespace fs = std::filesystem;
  const fs::path& out = options.out_dir;
  std::error_code ec;
  const std::string digest = scene_digest(scene);
  Checkpoint resume;
  if (options.resume) {
    if (fs::exists(out / "summary.json", ec)) {
      std::cerr << "mpm: " << out.string()
                << ": the run there is finished (summary.json); nothing to resume\n";
      return kExitBadInput;
    }
    try {
      resume = read_checkpoint(out / "checkpoint.h5");
      if (resume.text("run.scene_digest") != digest) {
        std::cerr << "mpm: " << scene.file.string() << ": changed since the checkpoint in "
                  << out.string() << " was written; run it afresh with --overwrite\n";
        return kExitBadInput;
      }
    } catch (const std::exception& e) {
      std::cerr << "mpm: " << out.string() << ": " << e.what() << '\n';
      return kExitBadInput;
    }
  } else if (fs::exists(out / "summary.json", ec) || fs::exists(out / "particles.h5", ec) ||
             fs::exists(frame_directory(out / "particles.h5"), ec)) {
    if (!options.overwrite) {
      std::cerr << "mpm: " << out.string()
                << ": holds an earlier result; choose another directory, pass --overwrite, or "
                   "--resume an unfinished run\n";
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
  ParticleFrame first;
  try {
    if (options.resume) {
      sim->restore_state(resume);
      const auto history_bytes =
          static_cast<std::uintmax_t>(resume.integer("run.history_bytes", 1)[0]);
      History::check_resumable(out / "history.csv", history_bytes);
      writer = std::make_unique<ParticleWriter>(
          out / "particles.h5", out / "particles.xmf",
          static_cast<std::size_t>(resume.integer("run.frames", 1)[0]));
      first = read_frame(out / "particles.h5", 0);  // through the index the writer rebuilt
      history = std::make_unique<History>(out / "history.csv", scene, *sim, history_bytes);
    } else {
      fs::create_directories(out);
      fs::remove(out / "checkpoint.h5", ec);  // an --overwrite run does not resume the old one
      writer = std::make_unique<ParticleWriter>(out / "particles.h5", out / "particles.xmf");
      history = std::make_unique<History>(out / "history.csv", scene, *sim);
    }
  } catch (const std::exception& e) {
    std::cerr << "mpm: " << out.string() << ": " << e.what() << '\n';
    return options.resume ? kExitBadInput : kExitIo;
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
  for (const DualWallSpec& wall : scene.dual_walls) {
    if (wall.method != CouplingMethod::one_way) continue;
    warnings.emplace_back(
        "wall \"" + wall.name +
        "\": one-way coupling gives the bulk the layer's velocity on Phi with no reaction on the "
        "layer, so it does not conserve momentum or energy (docs/benchmarks.md: thrown blocks "
        "gained energy); prefer mortar");
  }
  for (const auto& w : warnings) std::cerr << "mpm: warning: " << w << '\n';
  std::optional<std::string> failure;
  Progress progress(end, options.quiet);
  ForcePeaks peaks;
  std::unique_ptr<EnergyGuard> guard;
  double wall_before = 0.0;  // wall-clock seconds of the runs this one continues
  double output_seconds = 0.0;
  // Written with every particle frame, after it: a resumed run drops what came later.
  const auto checkpoint = [&]() {
    Checkpoint c;
    sim->save_state(c);
    c.texts["run.scene"] = fs::absolute(scene.file).string();
    c.texts["run.scene_digest"] = digest;
    c.texts["run.resolution"] = std::to_string(scene.resolution);
    c.reals["run.time"] = {t,
                           since_history,
                           next_output,
                           next_history,
                           min_dt,
                           max_dt,
                           wall_before + seconds_since(wall_start)};
    c.integers["run.step"] = {step};
    c.integers["run.frames"] = {static_cast<std::int64_t>(writer->frames_written())};
    c.integers["run.history_bytes"] = {static_cast<std::int64_t>(history->bytes())};
    c.reals["run.peak_force"] = flatten(peaks.force);
    c.reals["run.peak_time"] = peaks.time;
    c.reals["run.wall_impulse"] = flatten(peaks.impulse);
    c.reals["run.energy"] = guard->state();
    write_checkpoint(out / "checkpoint.h5", c);
  };

  try {
    if (options.resume) {
      const std::vector<double>& clock = resume.real("run.time", 7);
      t = clock[0];
      since_history = clock[1];
      next_output = clock[2];
      next_history = clock[3];
      min_dt = clock[4];
      max_dt = clock[5];
      wall_before = clock[6];
      step = static_cast<long>(resume.integer("run.step", 1)[0]);
      const std::vector<double>& force = resume.real("run.peak_force");
      peaks.force = unflatten(force);
      peaks.time = resume.real("run.peak_time", force.size() / 3);
      peaks.impulse = unflatten(resume.real("run.wall_impulse", force.size()));
      guard = std::make_unique<EnergyGuard>(scene, first);
      guard->restore(resume.real("run.energy", 2));
    } else {
      first = sim->frame(0.0, 0);
      writer->write(first);
      guard = std::make_unique<EnergyGuard>(scene, first);
      const Energies e0 = sim->energies();
      guard->start(e0.total(), e0.kinetic + e0.strain);
      // Each dual-grid wall's layer (cells, Gamma and Phi facets) for ParaView next to the
      // particles; only the geometry, not the coupling matrices (those are mpm prep's package).
      for (const DualWallSpec& wall : scene.dual_walls) {
        BoundaryPackage geometry;
        geometry.grid = wall.package->grid;
        geometry.layer = wall.package->layer;
        geometry.source = wall.package->source;
        save_boundary_package(geometry, out / ("wall_" + wall.name + ".h5"),
                              out / ("wall_" + wall.name + ".xmf"));
      }
      history->row(0.0, 0, 0.0, *sim, 0.0, e0);
      checkpoint();
    }
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
      const Clock::time_point output_start = Clock::now();
      if (scene.history_interval == 0.0 || t >= next_history - eps || t >= end - eps) {
        const Energies e = sim->energies();
        peaks.add(t, history->row(t, step, dt, *sim, since_history, e), sim->wall_impulses());
        sim->reset_wall_impulses();
        if (auto runaway = guard->check(e, *sim, scene, t, step)) {
          failure = "step " + std::to_string(step) + ", t = " + num(t) + ": " + *runaway;
          break;
        }
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
        checkpoint();
      }
      output_seconds += seconds_since(output_start);
      progress.update(t, step);
      if (options.halt_after_steps >= 0 && step >= options.halt_after_steps) return kExitOk;
    }
    if (!last_written && !failure) writer->write(sim->frame(t, step));
    writer->flush();
  } catch (const std::exception& e) {
    std::cerr << "\nmpm: " << out.string() << ": " << e.what() << '\n';
    return kExitIo;
  }
  progress.update(t, step, true);

  const double wall_seconds = wall_before + seconds_since(wall_start);
  nlohmann::json summary = {
      {"scene", scene.file.string()},
      {"name", scene.name},
      {"status", failure ? "failed" : "completed"},
      {"dimension", scene.dimension},
      {"resolution", scene.resolution},
      {"spacing", scene.spacing},
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
      {"phase_seconds", phase_json(sim->phase_times(), output_seconds)},
      {"final_energy", energy_json(sim->energies())},
      {"warnings", warnings},
  };
  if (failure) summary["error"] = *failure;
  if (options.resume) summary["resumed_from_step"] = resume.integer("run.step", 1)[0];
  const std::vector<std::string> walls = sim->wall_names();
  for (std::size_t i = 0; i < walls.size() && i < peaks.force.size(); ++i) {
    const Eigen::Vector3d& f = peaks.force[i];
    const Eigen::Vector3d& j = peaks.impulse[i];
    summary["walls"][walls[i]] = {{"peak_force", f.norm()},
                                  {"peak_force_time", peaks.time[i]},
                                  {"peak_force_vector", {f.x(), f.y(), f.z()}},
                                  {"impulse", j.norm()},
                                  {"impulse_vector", {j.x(), j.y(), j.z()}}};
  }
  // The dual-grid couplings' size and work (since this process started: a resumed run counts
  // from its resume), to see what a wall costs and what "multiplier_radius" saves.
  const std::vector<mpm::CouplingWork> couplings = sim->coupling_work();
  for (const mpm::CouplingWork& c : couplings) {
    summary["coupling"][c.wall] = {{"method", c.method},
                                   {"surface_nodes", c.surface_nodes},
                                   {"multipliers", c.multipliers},
                                   {"corner_nodes", c.corner_nodes},
                                   {"factorizations", c.factorizations},
                                   {"refinement_passes", c.refinement_passes},
                                   {"seconds",
                                    {{"assembly", c.assembly_seconds},
                                     {"analysis", c.analysis_seconds},
                                     {"factorization", c.factorization_seconds},
                                     {"solves", c.solve_seconds}}}};
    if (c.method == "enhanced") {
      summary["coupling"][c.wall]["active_set"] = {{"passes", c.active_set_passes},
                                                   {"unsettled_steps", c.unsettled_steps},
                                                   {"kept_released", c.kept_released}};
    } else {
      summary["coupling"][c.wall]["reshaped_steps"] = c.reshaped_steps;
      summary["coupling"][c.wall]["kept_steps"] = c.kept_steps;
    }
  }
  // Which way the couplings met the gather (the adaptive choice's record; the answers are the
  // same either way).
  if (!couplings.empty()) {
    const std::array<std::size_t, 2> ways = sim->coupling_overlap_counts();
    summary["coupling_overlap"] = {{"after", ways[0]}, {"beside", ways[1]}};
  }
  // The standard grid's memory: its node arrays are backed only where particles have been.
  const mpm::GridMemory g = sim->grid_memory();
  summary["grid_memory"] = {{"nodes", g.nodes},
                            {"box_bytes", g.box_bytes},
                            {"peak_bytes", g.peak_bytes},
                            {"active_blocks_bytes_at_peak", g.active_at_peak},
                            {"peak_active_blocks_bytes", g.peak_active}};
  summary["flow"] = flow_summary(scene, first, sim->frame(t, step));
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
