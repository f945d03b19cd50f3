#include "mpm/output.hpp"

#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>

#include "sync_file.hpp"

namespace fs = std::filesystem;

namespace {

// Each test gets its own directory (pid included: several build trees may run ctest at once).
class ParticleWriterTest : public ::testing::Test {
 protected:
  void SetUp() override {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    dir_ = fs::temp_directory_path() /
           ("mpm_test_output_" + std::string(info->name()) + "_" + std::to_string(::getpid()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  fs::path dir_;
};

// replace_file(), which every output file that must survive a kill goes through: the old file
// stays whole until the new one is complete, and a failed write leaves no temporary file.
class ReplaceFile : public ParticleWriterTest {};

TEST_F(ReplaceFile, KeepsTheOldFileUntilTheNewOneIsWhole) {
  const fs::path file = dir_ / "state.txt";
  auto write_text = [](const fs::path& path, const std::string& text) {
    std::ofstream out(path);
    out << text;
    return static_cast<bool>(out.flush());
  };
  ASSERT_TRUE(write_text(file, "old"));
  auto read = [&] {
    std::ifstream in(file);
    return std::string(std::istreambuf_iterator<char>(in), {});
  };
  for (const bool durable : {false, true}) {
    // Half written, then a failure: the old contents, and no FILE.tmp.
    EXPECT_FALSE(mpm::detail::replace_file(
        file, [&](const fs::path& tmp) { return write_text(tmp, "half") && false; }, durable));
    EXPECT_EQ(read(), "old");
    EXPECT_FALSE(fs::exists(dir_ / "state.txt.tmp"));
  }
  EXPECT_TRUE(mpm::detail::replace_file(
      file, [&](const fs::path& tmp) { return write_text(tmp, "new"); }, true));
  EXPECT_EQ(read(), "new");
  EXPECT_FALSE(fs::exists(dir_ / "state.txt.tmp"));
  // A file in a directory that does not exist: false, nothing made.
  EXPECT_FALSE(mpm::detail::replace_file(
      dir_ / "missing" / "x.txt", [&](const fs::path& tmp) { return write_text(tmp, "x"); }, true));
  EXPECT_FALSE(fs::exists(dir_ / "missing"));
}

// Deterministic, non-trivial values (negative, fractional, extreme) so an exact comparison proves
// nothing was converted or reordered on the way.
mpm::ParticleFrame make_frame(std::size_t count, double time, std::int64_t step) {
  mpm::ParticleFrame f;
  f.time = time;
  f.step = step;
  f.count = count;
  for (std::size_t i = 0; i < count; ++i) {
    const double s = static_cast<double>(i) + 0.1 * static_cast<double>(step);
    for (int c = 0; c < 3; ++c) {
      f.position.push_back(s + c / 3.0);
      f.velocity.push_back(-s * (c + 1) * 1e-7);
    }
    for (int c = 0; c < 9; ++c) f.stress.push_back((c - 4) * 1.5e6 + s);
    f.mass.push_back(i == 0 ? std::numeric_limits<double>::min() : 1.0 / (s + 1.0));
    f.volume.push_back(1e-9 * (s + 2.0));
    f.material.push_back(static_cast<int>(i % 3));
    f.body.push_back(i == 1 ? -1 : static_cast<int>(i) * 1000003);
  }
  return f;
}

void expect_equal(const mpm::ParticleFrame& a, const mpm::ParticleFrame& b) {
  EXPECT_EQ(a.time, b.time);
  EXPECT_EQ(a.step, b.step);
  EXPECT_EQ(a.count, b.count);
  EXPECT_EQ(a.position, b.position);
  EXPECT_EQ(a.velocity, b.velocity);
  EXPECT_EQ(a.stress, b.stress);
  EXPECT_EQ(a.mass, b.mass);
  EXPECT_EQ(a.volume, b.volume);
  EXPECT_EQ(a.material, b.material);
  EXPECT_EQ(a.body, b.body);
}

std::string slurp(const fs::path& path) {
  std::ifstream in(path);
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

std::size_t occurrences(const std::string& text, const std::string& needle) {
  std::size_t n = 0;
  for (auto pos = text.find(needle); pos != std::string::npos; pos = text.find(needle, pos + 1)) {
    ++n;
  }
  return n;
}

}  // namespace

using ParticleWriter = ParticleWriterTest;

TEST_F(ParticleWriter, RoundTripsFramesExactly) {
  const fs::path h5 = dir_ / "particles.h5";
  const std::vector<mpm::ParticleFrame> frames = {make_frame(0, 0.0, 0), make_frame(1, 0.25, 10),
                                                  make_frame(5, 0.5, 20)};
  {
    mpm::ParticleWriter writer(h5, dir_ / "particles.xmf");
    EXPECT_EQ(writer.frames_written(), 0U);
    for (const auto& f : frames) writer.write(f);
    EXPECT_EQ(writer.frames_written(), 3U);
    // Flushed after each frame, so readable while the writer is still open.
    EXPECT_EQ(mpm::count_frames(h5), 3U);
  }
  ASSERT_EQ(mpm::count_frames(h5), 3U);
  for (std::size_t i = 0; i < frames.size(); ++i) {
    SCOPED_TRACE("frame " + std::to_string(i));
    expect_equal(mpm::read_frame(h5, i), frames[i]);
  }
}

TEST_F(ParticleWriter, EmptyFileHasNoFrames) {
  const fs::path h5 = dir_ / "particles.h5";
  { mpm::ParticleWriter writer(h5, dir_ / "particles.xmf"); }
  EXPECT_EQ(mpm::count_frames(h5), 0U);
  EXPECT_THROW((void)mpm::read_frame(h5, 0), std::runtime_error);
  const std::string xmf = slurp(dir_ / "particles.xmf");
  EXPECT_NE(xmf.find("CollectionType=\"Temporal\""), std::string::npos);
  EXPECT_NE(xmf.find("</Xdmf>"), std::string::npos);
}

TEST_F(ParticleWriter, XdmfIndexesEveryFrame) {
  const fs::path xmf_path = dir_ / "particles.xmf";
  mpm::ParticleWriter writer(dir_ / "particles.h5", xmf_path);
  writer.write(make_frame(0, 0.0, 0));
  writer.write(make_frame(1, 0.25, 10));
  writer.write(make_frame(4, 1.5e-3, 20));

  ASSERT_TRUE(fs::exists(xmf_path));
  EXPECT_FALSE(fs::exists(dir_ / "particles.xmf.tmp"));
  const std::string xmf = slurp(xmf_path);
  EXPECT_NE(xmf.find("<Xdmf Version=\"3.0\">"), std::string::npos);
  EXPECT_NE(
      xmf.find("<Grid Name=\"Temporal\" GridType=\"Collection\" CollectionType=\"Temporal\">"),
      std::string::npos);
  EXPECT_EQ(occurrences(xmf, "GridType=\"Uniform\""), 3U);
  EXPECT_EQ(occurrences(xmf, "TopologyType=\"Polyvertex\""), 3U);
  EXPECT_NE(xmf.find("<Time Value=\"0\"/>"), std::string::npos);
  EXPECT_NE(xmf.find("<Time Value=\"0.25\"/>"), std::string::npos);
  EXPECT_NE(xmf.find("<Time Value=\"0.0015\"/>"), std::string::npos);
  EXPECT_NE(xmf.find("NumberOfElements=\"0\""), std::string::npos);
  EXPECT_NE(xmf.find("NumberOfElements=\"1\""), std::string::npos);
  EXPECT_NE(xmf.find("NumberOfElements=\"4\""), std::string::npos);
  for (const char* frame : {"000000", "000001", "000002"}) {
    for (const char* set :
         {"position", "velocity", "stress", "mass", "volume", "material", "body"}) {
      const std::string ref = std::string(">particles/") + frame + ".h5:/" + set + "<";
      EXPECT_EQ(occurrences(xmf, ref), 1U) << ref;
    }
  }
  EXPECT_NE(xmf.find("Dimensions=\"4 9\""), std::string::npos);
  EXPECT_NE(xmf.find("AttributeType=\"Tensor\""), std::string::npos);
  EXPECT_NE(xmf.find("NumberType=\"Int\""), std::string::npos);
}

// Both indexes list every frame, so they are rewritten after each frame only for the first 256
// (then within 2% of the writer's wall clock, which frames written back to back leave no room
// for once the index rewrites have taken their share); whatever the writer skipped, flush()
// and the destructor bring up to date: every frame is listed and reads back.
TEST_F(ParticleWriter, IndexesEveryFrameAtFirstAndAllFramesWhenFlushed) {
  const fs::path h5 = dir_ / "particles.h5";
  const fs::path xmf = dir_ / "particles.xmf";
  constexpr std::size_t kFrames = 300;
  {
    mpm::ParticleWriter writer(h5, xmf);
    for (std::size_t i = 0; i < kFrames; ++i) {
      writer.write(make_frame(1, 0.01 * static_cast<double>(i), static_cast<std::int64_t>(i)));
      ASSERT_EQ(writer.frames_written(), i + 1);
      ASSERT_LE(writer.frames_indexed(), writer.frames_written());
      if (i < 256) {
        ASSERT_EQ(writer.frames_indexed(), i + 1) << "frame " << i;
      }
    }
    // What the files on the disk say is what frames_indexed() says.
    EXPECT_EQ(mpm::count_frames(h5), writer.frames_indexed());
    EXPECT_EQ(occurrences(slurp(xmf), "GridType=\"Uniform\""), writer.frames_indexed());
    writer.flush();
    EXPECT_EQ(writer.frames_indexed(), kFrames);
    EXPECT_EQ(mpm::count_frames(h5), kFrames);
    EXPECT_EQ(occurrences(slurp(xmf), "GridType=\"Uniform\""), kFrames);
    writer.write(make_frame(2, 5.0, 500));  // one more, left to the destructor
  }
  ASSERT_EQ(mpm::count_frames(h5), kFrames + 1);
  EXPECT_EQ(occurrences(slurp(xmf), "GridType=\"Uniform\""), kFrames + 1);
  expect_equal(mpm::read_frame(h5, kFrames), make_frame(2, 5.0, 500));
  expect_equal(mpm::read_frame(h5, 257), make_frame(1, 0.01 * 257.0, 257));
}

TEST_F(ParticleWriter, XdmfReferencesH5RelativeToItsOwnDirectory) {
  fs::create_directories(dir_ / "data");
  mpm::ParticleWriter writer(dir_ / "data" / "run.h5", dir_ / "run.xmf");
  writer.write(make_frame(2, 1.0, 1));
  const std::string xmf = slurp(dir_ / "run.xmf");
  EXPECT_NE(xmf.find(">data/run/000000.h5:/position<"), std::string::npos) << xmf;
}

TEST_F(ParticleWriter, MissingDirectoryThrowsNamingTheFile) {
  const fs::path h5 = dir_ / "does-not-exist" / "particles.h5";
  try {
    mpm::ParticleWriter writer(h5, dir_ / "does-not-exist" / "particles.xmf");
    FAIL() << "expected std::runtime_error";
  } catch (const std::runtime_error& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find(h5.string()), std::string::npos) << what;
    EXPECT_EQ(what.find('\n'), std::string::npos) << what;
  }
}

TEST_F(ParticleWriter, ReadingMissingFileThrowsNamingTheFile) {
  const fs::path h5 = dir_ / "nothing.h5";
  try {
    (void)mpm::count_frames(h5);
    FAIL() << "expected std::runtime_error";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(h5.string()), std::string::npos) << e.what();
  }
}

TEST_F(ParticleWriter, OutOfRangeFrameThrows) {
  const fs::path h5 = dir_ / "particles.h5";
  {
    mpm::ParticleWriter writer(h5, dir_ / "particles.xmf");
    writer.write(make_frame(1, 0.0, 0));
    writer.write(make_frame(2, 0.1, 1));
  }
  EXPECT_NO_THROW((void)mpm::read_frame(h5, 1));
  EXPECT_THROW((void)mpm::read_frame(h5, 2), std::runtime_error);
  EXPECT_THROW((void)mpm::read_frame(h5, 1000000), std::runtime_error);
}

TEST_F(ParticleWriter, SizeMismatchThrowsInvalidArgumentAndWritesNothing) {
  const fs::path h5 = dir_ / "particles.h5";
  mpm::ParticleWriter writer(h5, dir_ / "particles.xmf");
  mpm::ParticleFrame bad = make_frame(3, 0.0, 0);
  bad.stress.pop_back();
  EXPECT_THROW(writer.write(bad), std::invalid_argument);
  bad = make_frame(3, 0.0, 0);
  bad.count = 4;
  EXPECT_THROW(writer.write(bad), std::invalid_argument);
  EXPECT_EQ(writer.frames_written(), 0U);

  // The writer stays usable and the next frame takes index 0.
  const mpm::ParticleFrame good = make_frame(3, 0.5, 7);
  writer.write(good);
  EXPECT_EQ(writer.frames_written(), 1U);
  ASSERT_EQ(mpm::count_frames(h5), 1U);
  expect_equal(mpm::read_frame(h5, 0), good);
}

// The frames are one file each (particles/NNNNNN.h5, written aside and renamed) and particles.h5
// is an index of external links rewritten the same way, so the output can be moved as a whole
// and read from anywhere: the links resolve against the index's own directory.
TEST_F(ParticleWriter, OutputReadsBackAfterTheDirectoryIsMoved) {
  const std::vector<mpm::ParticleFrame> frames = {make_frame(3, 0.0, 0), make_frame(3, 0.5, 4)};
  fs::create_directories(dir_ / "run");
  {
    mpm::ParticleWriter writer(dir_ / "run" / "particles.h5", dir_ / "run" / "particles.xmf");
    for (const auto& f : frames) writer.write(f);
  }
  EXPECT_TRUE(fs::exists(dir_ / "run" / "particles" / "000001.h5"));
  EXPECT_FALSE(fs::exists(dir_ / "run" / "particles" / "000001.h5.tmp"));
  EXPECT_FALSE(fs::exists(dir_ / "run" / "particles.h5.tmp"));
  fs::rename(dir_ / "run", dir_ / "moved");
  const fs::path h5 = dir_ / "moved" / "particles.h5";
  ASSERT_EQ(mpm::count_frames(h5), 2U);
  for (std::size_t i = 0; i < frames.size(); ++i) expect_equal(mpm::read_frame(h5, i), frames[i]);
}

// What a run killed at any moment leaves, and its resume from a checkpoint taken after frame 2:
// a frame written after the checkpoint, a half-written frame file and a half-written index
// beside the one the last frame left. The resumed writer keeps frames 0-2, drops the rest, and
// goes on from index 3.
TEST_F(ParticleWriter, ResumeKeepsTheCheckpointsFramesWhateverAKillLeft) {
  const fs::path h5 = dir_ / "particles.h5";
  const fs::path frames_dir = dir_ / "particles";
  std::vector<mpm::ParticleFrame> frames;
  {
    mpm::ParticleWriter writer(h5, dir_ / "particles.xmf");
    for (std::int64_t k = 0; k < 4; ++k) {
      frames.push_back(make_frame(4, 0.1 * static_cast<double>(k), k));
      writer.write(frames.back());
    }
  }
  std::ofstream(frames_dir / "000004.h5.tmp") << "half a frame";
  std::ofstream(dir_ / "particles.h5.tmp") << "half an index";
  {
    mpm::ParticleWriter writer(h5, dir_ / "particles.xmf", 3);
    EXPECT_EQ(writer.frames_written(), 3U);
    EXPECT_EQ(mpm::count_frames(h5), 3U);
    EXPECT_FALSE(fs::exists(frames_dir / "000003.h5"));
    EXPECT_FALSE(fs::exists(frames_dir / "000004.h5.tmp"));
    frames[3] = make_frame(2, 0.35, 9);
    writer.write(frames[3]);
  }
  ASSERT_EQ(mpm::count_frames(h5), 4U);
  for (std::size_t i = 0; i < frames.size(); ++i) {
    SCOPED_TRACE("frame " + std::to_string(i));
    expect_equal(mpm::read_frame(h5, i), frames[i]);
  }
  const std::string xmf = slurp(dir_ / "particles.xmf");
  EXPECT_EQ(occurrences(xmf, "GridType=\"Uniform\""), 4U);
  EXPECT_NE(xmf.find("<Time Value=\"0.35\"/>"), std::string::npos);
  EXPECT_EQ(xmf.find("<Time Value=\"0.30000000000000004\"/>"), std::string::npos);

  // Even an index destroyed outright is rebuilt: the frame files are what the resume needs.
  std::ofstream(h5, std::ios::trunc) << "not HDF5";
  mpm::ParticleWriter again(h5, dir_ / "particles.xmf", 2);
  EXPECT_EQ(mpm::count_frames(h5), 2U);
  expect_equal(mpm::read_frame(h5, 1), frames[1]);
}

TEST_F(ParticleWriter, ResumeWithoutTheCheckpointsFramesThrowsNamingTheFrameFile) {
  const fs::path h5 = dir_ / "particles.h5";
  {
    mpm::ParticleWriter writer(h5, dir_ / "particles.xmf");
    writer.write(make_frame(2, 0.0, 0));
    writer.write(make_frame(2, 0.1, 1));
  }
  const fs::path lost = dir_ / "particles" / "000001.h5";
  fs::remove(lost);
  try {
    mpm::ParticleWriter writer(h5, dir_ / "particles.xmf", 2);
    FAIL() << "expected std::runtime_error";
  } catch (const std::runtime_error& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find(lost.string()), std::string::npos) << what;
    EXPECT_EQ(what.find('\n'), std::string::npos) << what;
  }
  EXPECT_EQ(mpm::count_frames(h5), 2U) << "a refused resume leaves the index as it was";
  EXPECT_THROW((void)mpm::read_frame(h5, 1), std::runtime_error);
}

// A new writer truncates: an earlier run's frame files go with its index.
TEST_F(ParticleWriter, NewWriterDropsAnEarlierRunsFrames) {
  const fs::path h5 = dir_ / "particles.h5";
  {
    mpm::ParticleWriter writer(h5, dir_ / "particles.xmf");
    for (int k = 0; k < 3; ++k) writer.write(make_frame(1, k, k));
  }
  std::ofstream(dir_ / "particles" / "notes.txt") << "the user's";
  mpm::ParticleWriter writer(h5, dir_ / "particles.xmf");
  writer.write(make_frame(2, 0.0, 0));
  EXPECT_EQ(mpm::count_frames(h5), 1U);
  EXPECT_TRUE(fs::exists(dir_ / "particles" / "000000.h5"));
  EXPECT_FALSE(fs::exists(dir_ / "particles" / "000001.h5"));
  EXPECT_FALSE(fs::exists(dir_ / "particles" / "000002.h5"));
  EXPECT_TRUE(fs::exists(dir_ / "particles" / "notes.txt"));
}
