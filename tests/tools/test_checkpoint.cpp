// Checkpoint and restart (issue 10): a run stopped after N steps and resumed from its last
// checkpoint ends bit for bit where the uninterrupted run ends (single-threaded), with the same
// history; `mpm run` killed with SIGKILL at arbitrary moments and resumed each time gives the
// same result; and resuming what cannot be resumed is refused with one line.

#include <gtest/gtest.h>
#include <signal.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <string>
#include <thread>
#include <vector>

#include <tbb/global_control.h>
#include <nlohmann/json.hpp>

#include "mpm/output.hpp"
#include "mpm/run.hpp"
#include "mpm/scene.hpp"
#include "support/run_mpm.hpp"
#include "support/shapes.hpp"

namespace fs = std::filesystem;
using nlohmann::json;
using namespace mpm::test;  // NOLINT(google-build-using-namespace)

namespace {

/// A block sliding down a 30-degree dual-grid wall with friction, or (granular) a Drucker-Prager
/// block slumping on a box floor, whose plastic state must survive the restart too.
json scene(const std::string& wall_method) {
  json s = json::parse(R"({
    "dimension": 2,
    "grid": { "min": [0.0, 0.0], "max": [1.2, 1.0], "spacing": 0.05 },
    "shape_function": "bspline2",
    "scheme": { "update": "musl", "transfer": "apic" },
    "gravity": [0.0, -9.81],
    "materials": [
      { "name": "rubber", "model": "neo_hookean", "density": 1000, "youngs_modulus": 1.0e5,
        "poisson_ratio": 0.3 },
      { "name": "sand", "model": "drucker_prager", "density": 1800, "youngs_modulus": 1.0e5,
        "poisson_ratio": 0.3, "friction_angle": 30, "dilatancy_angle": 5 }
    ],
    "time": { "end": 0.12, "cfl": 0.4 },
    "output": { "interval": 0.01 }
  })");
  s["name"] = "checkpoint_" + wall_method;
  if (wall_method == "granular") {
    s["bodies"] = json::parse(R"([{ "name": "heap", "material": "sand",
        "shape": { "type": "box", "min": [0.4, 0.0], "max": [0.8, 0.4] } }])");
    s["walls"] = json::parse(R"([{ "face": "ymin", "condition": "friction", "mu": 0.4 }])");
  } else if (wall_method == "enhanced_3d") {
    // A block resting on a floor 0.3 h off the grid lines (the floor benchmark's, smaller).
    const double h = 0.1, base = 0.03;
    s["dimension"] = 3;
    s["grid"] = {{"min", {-h, -h, 0.0}}, {"max", {1.0 + h, 1.0 + h, 0.6}}, {"spacing", h}};
    s["gravity"] = {0.0, 0.0, -9.81};
    s["bodies"] = {
        {{"name", "block"},
         {"material", "rubber"},
         {"shape", {{"type", "box"}, {"min", {0.3, 0.3, base}}, {"max", {0.7, 0.7, base + 0.2}}}}}};
    s["walls"] = {{{"name", "floor"},
                   {"method", "enhanced"},
                   {"condition", "slip"},
                   {"separable", true},
                   {"surface",
                    {{"type", "mesh"},
                     {"file", mpm::test::floor_plane_file("mpm_checkpoint", base, -h, 1.0 + h)},
                     {"remesh", true}}}}};
  } else {
    // mortar_mls: the mortar scene under MLS-MPM (USL's order, its layer gather without the
    // light nodes).
    const bool mls = wall_method == "mortar_mls";
    if (mls) s["scheme"]["update"] = "mls";
    // Wall from (0.1, 0.8) down to (1.1, 0.2267): 30 degrees; block resting on it.
    s["bodies"] = json::parse(R"([{ "name": "block", "material": "rubber",
        "shape": { "type": "disk", "center": [0.35, 0.78], "radius": 0.1 } }])");
    s["walls"] = json::array(
        {{{"name", "incline"},
          {"method", mls ? "mortar" : wall_method},
          {"condition", "friction"},
          {"mu", 0.3},
          {"separable", true},
          {"surface", {{"type", "polyline"}, {"points", {{0.1, 0.8}, {1.1, 0.22265}}}}}}});
  }
  return s;
}

class Checkpoint : public ::testing::TestWithParam<const char*> {
 protected:
  void SetUp() override {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    std::string name = std::string(info->name()) + "_" + std::to_string(::getpid());
    for (char& c : name) {
      if (c == '/') c = '_';
    }
    dir_ = fs::temp_directory_path() / ("mpm_test_checkpoint_" + name);
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    scene_file_ = dir_ / "scene.json";
  }
  void TearDown() override { fs::remove_all(dir_); }

  /// Every frame of two runs equal to the last bit, and their histories byte for byte.
  static void expect_same_output(const fs::path& a, const fs::path& b) {
    EXPECT_EQ(read_text(a / "history.csv"), read_text(b / "history.csv"));
    const std::size_t frames = mpm::count_frames(a / "particles.h5");
    ASSERT_EQ(frames, mpm::count_frames(b / "particles.h5"));
    for (std::size_t i = 0; i < frames; ++i) {
      const mpm::ParticleFrame fa = mpm::read_frame(a / "particles.h5", i);
      const mpm::ParticleFrame fb = mpm::read_frame(b / "particles.h5", i);
      EXPECT_EQ(fa.time, fb.time) << "frame " << i;
      EXPECT_EQ(fa.position, fb.position) << "frame " << i;
      EXPECT_EQ(fa.velocity, fb.velocity) << "frame " << i;
      EXPECT_EQ(fa.stress, fb.stress) << "frame " << i;
      EXPECT_EQ(fa.volume, fb.volume) << "frame " << i;
    }
    const json sa = json::parse(read_text(a / "summary.json"));
    const json sb = json::parse(read_text(b / "summary.json"));
    EXPECT_EQ(sa["steps"], sb["steps"]);
    EXPECT_EQ(sa["walls"], sb["walls"]);  // peak forces and their times
    EXPECT_EQ(sa["flow"], sb["flow"]);
    EXPECT_EQ(sa["final_energy"], sb["final_energy"]);
  }

  fs::path dir_, scene_file_;
};

TEST_P(Checkpoint, StoppedAndResumedRunIsBitIdentical) {
  const tbb::global_control one_thread(tbb::global_control::max_allowed_parallelism, 1);
  write_text(scene_file_, scene(GetParam()).dump(2));
  const mpm::Scene s = mpm::load_scene(scene_file_);

  mpm::RunOptions whole;
  whole.out_dir = dir_ / "whole";
  whole.quiet = true;
  ASSERT_EQ(mpm::run_scene(s, whole), mpm::kExitOk);
  const long steps = json::parse(read_text(whole.out_dir / "summary.json"))["steps"];
  ASSERT_GT(steps, 20);

  // Stopped between two checkpoints, so the resumed run repeats the steps after the last one;
  // at three places in the run.
  for (const long halt : {steps / 3 + 1, steps / 2 + 3, 3 * steps / 4}) {
    mpm::RunOptions part = whole;
    part.out_dir = dir_ / ("part_" + std::to_string(halt));
    part.halt_after_steps = halt;
    ASSERT_EQ(mpm::run_scene(s, part), mpm::kExitOk);
    ASSERT_FALSE(fs::exists(part.out_dir / "summary.json"));
    ASSERT_TRUE(fs::exists(part.out_dir / "checkpoint.h5"));
    part.halt_after_steps = -1;
    part.resume = true;
    ASSERT_EQ(mpm::run_scene(s, part), mpm::kExitOk);
    SCOPED_TRACE("halted after step " + std::to_string(halt));
    expect_same_output(whole.out_dir, part.out_dir);
  }
}

// Enhanced restarts its contact active set from the last step's, and its two solvers from the
// factorisations the uninterrupted run has in hand (maybe an earlier step's, which it refines
// against): the checkpoint keeps those matrices and the restore factorises them again. Without
// them the resumed run factorised afresh and parted from the uninterrupted one in the 10th digit.
// On a 3D floor the contact matrix's pattern changes from step to step while its unknowns do
// not, and Enhanced refines across such changes: the checkpoint keeps the enhancement nodes of
// the factorisation in hand too (without them the resumed run formed and factorised the matrix
// anew and parted from the uninterrupted one, halted after steps 116-128 of 155).
INSTANTIATE_TEST_SUITE_P(Walls, Checkpoint,
                         ::testing::Values("mortar", "granular", "enhanced", "enhanced_3d",
                                           "mortar_mls"));

/// The inode of `file` (0 if absent): a checkpoint is renamed into place, so a new one is a new
/// inode.
ino_t inode(const fs::path& file) {
  struct stat st {};
  return ::stat(file.c_str(), &st) == 0 ? st.st_ino : 0;
}

/// Starts `mpm ARGS` and kills it with SIGKILL `delay` after it has written a checkpoint of its
/// own (`checkpoint` replaced), or `delay` after its start if `checkpoint` is empty; returns
/// false if it ended first. Waiting for its own checkpoint makes every kill land in a run that
/// has made progress, however slow the machine (a sanitizer build on a loaded machine spent
/// all of fixed 40-300 ms delays starting up, and the test then resumed from no checkpoint).
bool kill_after(const std::vector<std::string>& args, std::chrono::milliseconds delay,
                const fs::path& checkpoint = {}) {
  const ino_t before = checkpoint.empty() ? 0 : inode(checkpoint);
  const pid_t pid = start_mpm(args);
  if (pid < 0) return false;
  int status = 0;
  if (!checkpoint.empty()) {
    const auto give_up = std::chrono::steady_clock::now() + std::chrono::minutes(5);
    while (inode(checkpoint) == before || inode(checkpoint) == 0) {
      if (::waitpid(pid, &status, WNOHANG) == pid) return false;  // it ended first
      if (std::chrono::steady_clock::now() > give_up) {
        ADD_FAILURE() << "no checkpoint written in 5 minutes";
        break;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
  }
  std::this_thread::sleep_for(delay);
  ::kill(pid, SIGKILL);
  ::waitpid(pid, &status, 0);
  return WIFSIGNALED(status);
}

class KilledRun : public Checkpoint {};

TEST_F(KilledRun, ResumesAfterSigkillAtArbitraryMoments) {
  json s = scene("mortar");
  s["grid"]["spacing"] = 0.01;  // about 3 s on one core: kills land inside the run
  s["time"]["end"] = 0.3;
  s["output"]["interval"] = 0.002;  // a frame and a checkpoint every few steps: kills hit writes
  write_text(scene_file_, s.dump(2));
  const fs::path whole = dir_ / "whole", part = dir_ / "part";
  const RunResult reference =
      run_mpm({"run", scene_file_.string(), "-o", whole.string(), "-q", "-j", "1"});
  ASSERT_EQ(reference.exit_code, 0) << reference.err;

  // Fixed pseudo-random delays, so a failure can be rerun. The first kill, 40 ms after the
  // start, may land before the first checkpoint exists; the run is then started again rather
  // than resumed. Every later kill comes its delay after the run's first checkpoint of its own.
  const std::vector<std::string> fresh = {
      "run", scene_file_.string(), "-o", part.string(), "-q", "-j", "1", "--overwrite"};
  const std::vector<std::string> resume = {"run", "--resume", part.string(), "-q", "-j", "1"};
  int kills = 0;
  bool started = false;
  for (const int ms : {40, 170, 95, 260, 130, 210, 60, 300}) {
    const fs::path wait_for = kills == 0 ? fs::path() : part / "checkpoint.h5";
    if (!kill_after(started ? resume : fresh, std::chrono::milliseconds(ms), wait_for)) break;
    ++kills;
    started = fs::exists(part / "checkpoint.h5");
  }
  EXPECT_GE(kills, 3);
  std::printf("killed %d times\n", kills);
  if (!fs::exists(part / "summary.json")) {
    const RunResult last = run_mpm(started ? resume : fresh);
    ASSERT_EQ(last.exit_code, 0) << last.err;
  }
  expect_same_output(whole, part);
}

// A history cut short after its checkpoint was written (a power cut can take a file's tail) is
// refused, not padded: extending it would add rows of zero bytes that look written.
TEST_F(KilledRun, RefusesAHistoryShorterThanItsCheckpoint) {
  write_text(scene_file_, scene("mortar").dump(2));
  mpm::RunOptions part;
  part.out_dir = dir_ / "part";
  part.quiet = true;
  part.halt_after_steps = 30;
  ASSERT_EQ(mpm::run_scene(mpm::load_scene(scene_file_), part), mpm::kExitOk);
  const fs::path history = part.out_dir / "history.csv";
  const std::string text = read_text(history);
  const fs::path later = part.out_dir / "particles" / "000099.h5";
  write_text(later, "a frame written after the checkpoint");
  ASSERT_GT(text.size(), 100U);
  write_text(history, text.substr(0, text.size() / 2));
  const RunResult r = run_mpm({"run", "--resume", part.out_dir.string(), "-q"});
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_TRUE(contains(r.err, history.string())) << r.err;
  EXPECT_TRUE(contains(r.err, "fewer than")) << r.err;
  EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
  EXPECT_EQ(read_text(history), text.substr(0, text.size() / 2));  // not padded
  // Refused before the resume changed anything: a frame after the checkpoint is still there.
  EXPECT_EQ(read_text(later), "a frame written after the checkpoint");
}

TEST_F(KilledRun, RefusesWhatCannotBeResumed) {
  write_text(scene_file_, scene("mortar").dump(2));
  const fs::path out = dir_ / "out";
  // No checkpoint there.
  RunResult r = run_mpm({"run", "--resume", out.string(), "-q"});
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(contains(r.err, "checkpoint.h5")) << r.err;
  EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
  // A finished run.
  ASSERT_EQ(run_mpm({"run", scene_file_.string(), "-o", out.string(), "-q"}).exit_code, 0);
  const std::string history = read_text(out / "history.csv");
  r = run_mpm({"run", "--resume", out.string(), "-q"});
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(contains(r.err, "finished")) << r.err;
  // A scene edited since the checkpoint.
  fs::remove(out / "summary.json");
  json edited = scene("mortar");
  edited["materials"][0]["density"] = 1100;
  write_text(scene_file_, edited.dump(2));
  r = run_mpm({"run", "--resume", out.string(), "-q"});
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(contains(r.err, scene_file_.string() + ": changed since the checkpoint")) << r.err;
  EXPECT_EQ(read_text(out / "history.csv"), history);  // nothing written is lost
  // A scene and --resume together.
  r = run_mpm({"run", scene_file_.string(), "--resume", out.string()});
  EXPECT_EQ(r.exit_code, 2);
}

}  // namespace
