#include "mpm/output.hpp"

#include "hdf5_util.hpp"
#include "sync_file.hpp"

#include <algorithm>
#include <array>
#include <charconv>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <optional>
#include <stdexcept>
#include <string>
#include <system_error>
#include <utility>

namespace mpm {
namespace {

using namespace detail;  // NOLINT(google-build-using-namespace): HDF5 helpers

// The frame's int vectors are written as 32-bit integers; make the memory type match exactly.
static_assert(sizeof(int) == 4, "material/body are stored as int32");

std::string frame_name(std::size_t index) {
  std::array<char, 32> buf{};
  std::snprintf(buf.data(), buf.size(), "%06zu", index);
  return buf.data();
}

Handle open_for_reading(const std::filesystem::path& h5_path) {
  silence_hdf5();
  Handle file(H5Fopen(h5_path.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT), H5Fclose);
  if (!file.ok()) throw std::runtime_error("cannot open HDF5 file " + quoted(h5_path));
  return file;
}

// Frame group names in numeric order: sorting by (length, text) keeps "1000000" after "999999"
// should a run ever outgrow the six-digit padding.
std::vector<std::string> frame_names(hid_t file, const std::filesystem::path& h5_path) {
  const Handle frames(H5Gopen2(file, "/frames", H5P_DEFAULT), H5Gclose);
  std::vector<std::string> names;
  if (!frames.ok() || !link_names(frames.get(), names)) {
    throw std::runtime_error("no /frames group in HDF5 file " + quoted(h5_path));
  }
  std::sort(names.begin(), names.end(), [](const std::string& a, const std::string& b) {
    return a.size() != b.size() ? a.size() < b.size() : a < b;
  });
  return names;
}

void check_sizes(const ParticleFrame& frame) {
  const std::size_t n = frame.count;
  const auto check = [](bool good, const char* field) {
    if (!good) {
      throw std::invalid_argument(std::string("ParticleFrame::") + field +
                                  " size does not match count");
    }
  };
  check(frame.position.size() == 3 * n, "position");
  check(frame.velocity.size() == 3 * n, "velocity");
  check(frame.stress.size() == 9 * n, "stress");
  check(frame.mass.size() == n, "mass");
  check(frame.volume.size() == n, "volume");
  check(frame.material.size() == n, "material");
  check(frame.body.size() == n, "body");
}

// Frame files are named by their index: NNNNNN.h5 (six digits, more once a run outgrows them).
// Returns the index, or nothing for any other name.
std::optional<std::size_t> frame_index(const std::string& file_name) {
  const std::size_t digits = file_name.size() - std::min<std::size_t>(file_name.size(), 3);
  if (digits < 6 || file_name.compare(digits, 3, ".h5") != 0) return std::nullopt;
  std::size_t index = 0;
  const auto [end, error] = std::from_chars(file_name.data(), file_name.data() + digits, index);
  if (error != std::errc{} || end != file_name.data() + digits) return std::nullopt;
  return index;
}

}  // namespace

std::filesystem::path frame_directory(const std::filesystem::path& h5_path) {
  return h5_path.parent_path() / h5_path.stem();
}

struct ParticleWriter::Impl {
  using Clock = std::chrono::steady_clock;
  // Both indexes list every frame, so rewriting them costs in proportion to the frames written:
  // after every frame that made a run's output quadratic in its frames (19.5 ms a frame at 3,000
  // frames, 2.7 ms at 500: docs/performance.md). They are rewritten after every frame while the
  // run has at most kAlwaysIndexed (a few milliseconds at most), later only while the time spent
  // rewriting them since then, the next rewrite included, stays within kIndexShare of the wall
  // clock since then, and always by flush().
  static constexpr std::size_t kAlwaysIndexed = 256;
  static constexpr double kIndexShare = 0.02;

  std::filesystem::path h5_path;    // the index: /frames/NNNNNN, external links to the frames
  std::filesystem::path frame_dir;  // one file per frame, NNNNNN.h5
  std::filesystem::path xmf_path;
  std::string frame_ref;  // frame_dir as seen from the xmf's directory, XML-escaped
  std::string grids;      // XDMF <Grid> blocks of all frames so far; the index is rebuilt from this
  std::size_t frames = 0;
  std::size_t indexed = 0;         // the frames the indexes on the disk list
  Clock::time_point budget_start;  // the last rewrite of the first kAlwaysIndexed frames
  double index_seconds = 0.0;      // spent rewriting the indexes since, and on the last one
  double last_index_seconds = 0.0;

  Impl(std::filesystem::path h5, std::filesystem::path xmf)
      : h5_path(std::move(h5)), frame_dir(frame_directory(h5_path)), xmf_path(std::move(xmf)) {}

  [[nodiscard]] std::filesystem::path frame_file(std::size_t index) const {
    return frame_dir / (frame_name(index) + ".h5");
  }

  std::string data_item(const std::string& group, const char* name, std::size_t count,
                        std::size_t components, bool is_int) const {
    std::string dims = std::to_string(count);
    if (components > 1) dims += " " + std::to_string(components);
    return "          <DataItem Dimensions=\"" + dims + "\" NumberType=\"" +
           (is_int ? R"(Int" Precision="4")" : R"(Float" Precision="8")") + R"( Format="HDF">)" +
           frame_ref + "/" + group + ".h5:/" + name + "</DataItem>\n";
  }

  std::string attribute(const std::string& group, const char* name, const char* type,
                        std::size_t count, std::size_t components, bool is_int) const {
    return std::string("        <Attribute Name=\"") + name + "\" AttributeType=\"" + type +
           "\" Center=\"Node\">\n" + data_item(group, name, count, components, is_int) +
           "        </Attribute>\n";
  }

  void append_grid(const ParticleFrame& frame, const std::string& group) {
    const std::size_t n = frame.count;
    grids += "      <Grid Name=\"frame_" + group + "\" GridType=\"Uniform\">\n";
    grids += "        <Time Value=\"" + format_double(frame.time) + "\"/>\n";
    grids += R"(        <Topology TopologyType="Polyvertex" NumberOfElements=")" +
             std::to_string(n) + "\"/>\n";
    grids += "        <Geometry GeometryType=\"XYZ\">\n" +
             data_item(group, "position", n, 3, false) + "        </Geometry>\n";
    grids += attribute(group, "velocity", "Vector", n, 3, false);
    grids += attribute(group, "stress", "Tensor", n, 9, false);
    grids += attribute(group, "mass", "Scalar", n, 1, false);
    grids += attribute(group, "volume", "Scalar", n, 1, false);
    grids += attribute(group, "material", "Scalar", n, 1, true);
    grids += attribute(group, "body", "Scalar", n, 1, true);
    grids += "      </Grid>\n";
  }

  // XDMF resolves HDF paths against the xmf's own directory, so keep the two relocatable together.
  void set_reference() {
    std::filesystem::path dir = xmf_path.parent_path();
    if (dir.empty()) dir = ".";
    std::error_code error;
    std::filesystem::path ref = std::filesystem::relative(frame_dir, dir, error);
    if (error || ref.empty()) ref = std::filesystem::absolute(frame_dir);
    frame_ref = xml_escape(ref.generic_string());
  }

  // Written aside and renamed over the old index so a reader never sees a half-written file.
  void write_xmf() const {
    const auto write = [&](const std::filesystem::path& tmp) {
      std::ofstream out(tmp, std::ios::trunc);
      out << "<?xml version=\"1.0\" ?>\n<!DOCTYPE Xdmf SYSTEM \"Xdmf.dtd\" []>\n"
             "<Xdmf Version=\"3.0\">\n  <Domain>\n"
             "    <Grid Name=\"Temporal\" GridType=\"Collection\" CollectionType=\"Temporal\">\n"
          << grids << "    </Grid>\n  </Domain>\n</Xdmf>\n";
      out.close();
      return static_cast<bool>(out);
    };
    if (!replace_file(xmf_path, write, false)) {
      throw std::runtime_error("cannot write XDMF file " + quoted(xmf_path));
    }
  }

  // The HDF5 index of the first `count` frames, written aside and renamed over the old one like
  // the XDMF index: HDF5 updates a file in place, and a process killed while it does (or while
  // freed space is reused before a flush) can leave the file's links pointing at garbage. So no
  // HDF5 file is ever changed once written: a frame file is complete or absent, and the index is
  // the old one or the new one, whatever moment a run is killed at.
  void write_index(std::size_t count) const {
    const std::string dir = frame_dir.filename().generic_string();
    const auto write = [&](const std::filesystem::path& tmp) {
      Handle file(H5Fcreate(tmp.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT), H5Fclose);
      Handle group(file.ok()
                       ? H5Gcreate2(file.get(), "/frames", H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT)
                       : H5I_INVALID_HID,
                   H5Gclose);
      bool good = group.ok();
      for (std::size_t i = 0; good && i < count; ++i) {
        const std::string name = frame_name(i);
        good = H5Lcreate_external((dir + "/" + name + ".h5").c_str(), "/", group.get(),
                                  name.c_str(), H5P_DEFAULT, H5P_DEFAULT) >= 0;
      }
      good = group.close() && good;
      return file.close() && good;
    };
    if (!replace_file(h5_path, write, false)) {
      throw std::runtime_error("cannot write HDF5 file " + quoted(h5_path));
    }
  }

  void write_indexes() {
    const Clock::time_point start = Clock::now();
    write_index(frames);
    write_xmf();
    const Clock::time_point end = Clock::now();
    last_index_seconds = std::chrono::duration<double>(end - start).count();
    indexed = frames;
    if (frames <= kAlwaysIndexed) {
      budget_start = end;
      index_seconds = 0.0;
    } else {
      index_seconds += last_index_seconds;
    }
  }

  [[nodiscard]] bool index_due() const {
    if (frames <= kAlwaysIndexed) return true;
    const double since = std::chrono::duration<double>(Clock::now() - budget_start).count();
    return index_seconds + last_index_seconds <= kIndexShare * since;
  }

  // Written aside and renamed when complete, on the disk before the checkpoint that counts it
  // (written after it) is: a resume after a power cut finds every frame it needs.
  void write_frame(const ParticleFrame& frame, const std::filesystem::path& path) const {
    const auto write = [&](const std::filesystem::path& tmp) {
      Handle file(H5Fcreate(tmp.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT), H5Fclose);
      const hid_t id = file.get();
      const std::size_t n = frame.count;
      const bool good =
          file.ok() && write_attribute(id, "time", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.time) &&
          write_attribute(id, "step", H5T_STD_I64LE, H5T_NATIVE_INT64, frame.step) &&
          write_dataset(id, "position", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.position.data(), n,
                        3) &&
          write_dataset(id, "velocity", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.velocity.data(), n,
                        3) &&
          write_dataset(id, "stress", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.stress.data(), n,
                        9) &&
          write_dataset(id, "mass", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.mass.data(), n, 1) &&
          write_dataset(id, "volume", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.volume.data(), n,
                        1) &&
          write_dataset(id, "material", H5T_STD_I32LE, H5T_NATIVE_INT, frame.material.data(), n,
                        1) &&
          write_dataset(id, "body", H5T_STD_I32LE, H5T_NATIVE_INT, frame.body.data(), n, 1);
      return file.close() && good;
    };
    if (!replace_file(path, write, true)) {
      throw std::runtime_error("cannot write frame file " + quoted(path));
    }
  }

  // Frame files numbered `first` or later, and unfinished ones (*.tmp), in the frame directory.
  void remove_frames_from(std::size_t first) const {
    std::error_code error;
    std::vector<std::filesystem::path> stale;
    for (const auto& entry : std::filesystem::directory_iterator(frame_dir, error)) {
      const std::string name = entry.path().filename().string();
      const std::optional<std::size_t> index = frame_index(name);
      const bool unfinished = name.size() > 7 && name.compare(name.size() - 7, 7, ".h5.tmp") == 0;
      if ((index && *index >= first) || unfinished) stale.push_back(entry.path());
    }
    if (error) throw std::runtime_error("cannot list directory " + quoted(frame_dir));
    for (const auto& path : stale) {
      if (!std::filesystem::remove(path, error) && error) {
        throw std::runtime_error("cannot remove frame file " + quoted(path));
      }
    }
  }
};

ParticleWriter::ParticleWriter(const std::filesystem::path& h5_path,
                               const std::filesystem::path& xmf_path)
    : impl_(std::make_unique<Impl>(h5_path, xmf_path)) {
  silence_hdf5();
  Impl& im = *impl_;
  std::error_code error;
  // Not create_directories: a missing output directory is the caller's error, not ours to make.
  std::filesystem::create_directory(im.frame_dir, error);
  if (error) throw std::runtime_error("cannot create HDF5 file " + quoted(h5_path));
  im.remove_frames_from(0);  // an earlier run's, as the index is truncated
  im.set_reference();
  im.write_indexes();
}

ParticleWriter::ParticleWriter(const std::filesystem::path& h5_path,
                               const std::filesystem::path& xmf_path, std::size_t keep_frames)
    : impl_(std::make_unique<Impl>(h5_path, xmf_path)) {
  silence_hdf5();
  Impl& im = *impl_;
  im.set_reference();
  for (std::size_t i = 0; i < keep_frames; ++i) {
    // The XDMF index needs each frame's time and particle count only.
    const std::filesystem::path path = im.frame_file(i);
    const Handle file(H5Fopen(path.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT), H5Fclose);
    ParticleFrame header;
    const Handle set(file.ok() ? H5Dopen2(file.get(), "mass", H5P_DEFAULT) : H5I_INVALID_HID,
                     H5Dclose);
    const Handle space(set.ok() ? H5Dget_space(set.get()) : H5I_INVALID_HID, H5Sclose);
    hsize_t count = 0;
    if (!space.ok() || !read_attribute(file.get(), "time", H5T_NATIVE_DOUBLE, header.time) ||
        H5Sget_simple_extent_dims(space.get(), &count, nullptr) != 1) {
      throw std::runtime_error("cannot read frame file " + quoted(path) + " (the checkpoint has " +
                               std::to_string(keep_frames) + " frames)");
    }
    header.count = count;
    im.append_grid(header, frame_name(i));
  }
  im.remove_frames_from(keep_frames);  // written after the checkpoint
  im.frames = keep_frames;
  im.write_indexes();
}

ParticleWriter::~ParticleWriter() {
  // The caller flushes to hear of a failure; here (an exception on its way out) the indexes are
  // brought up to date if they can be, and a resume rebuilds them from the frame files if not.
  try {
    flush();
  } catch (const std::exception&) {  // NOLINT(bugprone-empty-catch): nothing to report it to
  }
}

void ParticleWriter::write(const ParticleFrame& frame) {
  check_sizes(frame);
  silence_hdf5();
  Impl& im = *impl_;
  im.write_frame(frame, im.frame_file(im.frames));
  ++im.frames;
  im.append_grid(frame, frame_name(im.frames - 1));
  if (im.index_due()) im.write_indexes();
}

void ParticleWriter::flush() {
  Impl& im = *impl_;
  if (im.indexed == im.frames) return;
  silence_hdf5();
  im.write_indexes();
}

std::size_t ParticleWriter::frames_indexed() const { return impl_->indexed; }

std::size_t ParticleWriter::frames_written() const { return impl_->frames; }

ParticleFrame read_frame(const std::filesystem::path& h5_path, std::size_t index) {
  const Handle file = open_for_reading(h5_path);
  const std::vector<std::string> names = frame_names(file.get(), h5_path);
  if (index >= names.size()) {
    throw std::runtime_error("frame " + std::to_string(index) + " out of range (" +
                             std::to_string(names.size()) + " frames) in HDF5 file " +
                             quoted(h5_path));
  }
  const Handle g(H5Gopen2(file.get(), ("/frames/" + names[index]).c_str(), H5P_DEFAULT), H5Gclose);
  const hid_t id = g.get();
  ParticleFrame frame;
  std::array<std::size_t, 7> counts{};
  const bool good =
      g.ok() && read_attribute(id, "time", H5T_NATIVE_DOUBLE, frame.time) &&
      read_attribute(id, "step", H5T_NATIVE_INT64, frame.step) &&
      read_dataset(id, "position", H5T_NATIVE_DOUBLE, 3, counts[0], frame.position) &&
      read_dataset(id, "velocity", H5T_NATIVE_DOUBLE, 3, counts[1], frame.velocity) &&
      read_dataset(id, "stress", H5T_NATIVE_DOUBLE, 9, counts[2], frame.stress) &&
      read_dataset(id, "mass", H5T_NATIVE_DOUBLE, 1, counts[3], frame.mass) &&
      read_dataset(id, "volume", H5T_NATIVE_DOUBLE, 1, counts[4], frame.volume) &&
      read_dataset(id, "material", H5T_NATIVE_INT, 1, counts[5], frame.material) &&
      read_dataset(id, "body", H5T_NATIVE_INT, 1, counts[6], frame.body) &&
      std::all_of(counts.begin(), counts.end(), [&](std::size_t c) { return c == counts[0]; });
  if (!good) {
    // Its data are in the frame file the link names (runs before the frame files held them in
    // the group itself, which reads the same way).
    throw std::runtime_error("cannot read frame /frames/" + names[index] + " of HDF5 file " +
                             quoted(h5_path) + " (frame file " +
                             quoted(frame_directory(h5_path) / (names[index] + ".h5")) + ")");
  }
  frame.count = counts[0];
  return frame;
}

std::size_t count_frames(const std::filesystem::path& h5_path) {
  const Handle file = open_for_reading(h5_path);
  return frame_names(file.get(), h5_path).size();
}

}  // namespace mpm
