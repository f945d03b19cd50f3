#include "mpm/output.hpp"

#include "hdf5_util.hpp"

#include <algorithm>
#include <array>
#include <charconv>
#include <cstdio>
#include <fstream>
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

}  // namespace

struct ParticleWriter::Impl {
  std::filesystem::path h5_path;
  std::filesystem::path xmf_path;
  std::string h5_ref;  // h5 file as seen from the xmf's directory, XML-escaped
  Handle file{H5I_INVALID_HID, H5Fclose};
  std::string grids;  // XDMF <Grid> blocks of all frames so far; the index is rebuilt from this
  std::size_t frames = 0;

  Impl(std::filesystem::path h5, std::filesystem::path xmf)
      : h5_path(std::move(h5)), xmf_path(std::move(xmf)) {}

  std::string data_item(const std::string& group, const char* name, std::size_t count,
                        std::size_t components, bool is_int) const {
    std::string dims = std::to_string(count);
    if (components > 1) dims += " " + std::to_string(components);
    return "          <DataItem Dimensions=\"" + dims + "\" NumberType=\"" +
           (is_int ? R"(Int" Precision="4")" : R"(Float" Precision="8")") + R"( Format="HDF">)" +
           h5_ref + ":/frames/" + group + "/" + name + "</DataItem>\n";
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
    std::filesystem::path ref = std::filesystem::relative(h5_path, dir, error);
    if (error || ref.empty()) ref = std::filesystem::absolute(h5_path);
    h5_ref = xml_escape(ref.generic_string());
  }

  // Written aside and renamed over the old index so a reader never sees a half-written file.
  void write_xmf() const {
    std::filesystem::path tmp = xmf_path;
    tmp += ".tmp";
    {
      std::ofstream out(tmp, std::ios::trunc);
      out << "<?xml version=\"1.0\" ?>\n<!DOCTYPE Xdmf SYSTEM \"Xdmf.dtd\" []>\n"
             "<Xdmf Version=\"3.0\">\n  <Domain>\n"
             "    <Grid Name=\"Temporal\" GridType=\"Collection\" CollectionType=\"Temporal\">\n"
          << grids << "    </Grid>\n  </Domain>\n</Xdmf>\n";
      out.close();
      if (!out) throw std::runtime_error("cannot write XDMF file " + quoted(xmf_path));
    }
    std::error_code error;
    std::filesystem::rename(tmp, xmf_path, error);
    if (error) throw std::runtime_error("cannot write XDMF file " + quoted(xmf_path));
  }

  void write_frame(const ParticleFrame& frame, const std::string& group) {
    const Handle g(
        H5Gcreate2(file.get(), ("/frames/" + group).c_str(), H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT),
        H5Gclose);
    const hid_t id = g.get();
    const std::size_t n = frame.count;
    const bool good =
        g.ok() && write_attribute(id, "time", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.time) &&
        write_attribute(id, "step", H5T_STD_I64LE, H5T_NATIVE_INT64, frame.step) &&
        write_dataset(id, "position", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.position.data(), n,
                      3) &&
        write_dataset(id, "velocity", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.velocity.data(), n,
                      3) &&
        write_dataset(id, "stress", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.stress.data(), n, 9) &&
        write_dataset(id, "mass", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.mass.data(), n, 1) &&
        write_dataset(id, "volume", H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, frame.volume.data(), n, 1) &&
        write_dataset(id, "material", H5T_STD_I32LE, H5T_NATIVE_INT, frame.material.data(), n, 1) &&
        write_dataset(id, "body", H5T_STD_I32LE, H5T_NATIVE_INT, frame.body.data(), n, 1);
    if (!good) throw std::runtime_error("cannot write frame to HDF5 file " + quoted(h5_path));
  }
};

ParticleWriter::ParticleWriter(const std::filesystem::path& h5_path,
                               const std::filesystem::path& xmf_path)
    : impl_(std::make_unique<Impl>(h5_path, xmf_path)) {
  silence_hdf5();
  Impl& im = *impl_;
  im.file = Handle(H5Fcreate(h5_path.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT), H5Fclose);
  if (!im.file.ok()) throw std::runtime_error("cannot create HDF5 file " + quoted(h5_path));
  const Handle frames(H5Gcreate2(im.file.get(), "/frames", H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT),
                      H5Gclose);
  if (!frames.ok() || H5Fflush(im.file.get(), H5F_SCOPE_GLOBAL) < 0) {
    throw std::runtime_error("cannot write HDF5 file " + quoted(h5_path));
  }
  im.set_reference();
  im.write_xmf();
}

ParticleWriter::ParticleWriter(const std::filesystem::path& h5_path,
                               const std::filesystem::path& xmf_path, std::size_t keep_frames)
    : impl_(std::make_unique<Impl>(h5_path, xmf_path)) {
  silence_hdf5();
  Impl& im = *impl_;
  im.file = Handle(H5Fopen(h5_path.c_str(), H5F_ACC_RDWR, H5P_DEFAULT), H5Fclose);
  if (!im.file.ok()) throw std::runtime_error("cannot open HDF5 file " + quoted(h5_path));
  const std::vector<std::string> names = frame_names(im.file.get(), h5_path);
  if (names.size() < keep_frames) {
    throw std::runtime_error("HDF5 file " + quoted(h5_path) + " holds " +
                             std::to_string(names.size()) + " frames, the checkpoint " +
                             std::to_string(keep_frames));
  }
  for (std::size_t i = keep_frames; i < names.size(); ++i) {
    if (H5Ldelete(im.file.get(), ("/frames/" + names[i]).c_str(), H5P_DEFAULT) < 0) {
      throw std::runtime_error("cannot write HDF5 file " + quoted(h5_path));
    }
  }
  im.set_reference();
  for (std::size_t i = 0; i < keep_frames; ++i) {
    // The index needs each frame's time and particle count only.
    const Handle g(H5Gopen2(im.file.get(), ("/frames/" + names[i]).c_str(), H5P_DEFAULT), H5Gclose);
    ParticleFrame header;
    const Handle set(g.ok() ? H5Dopen2(g.get(), "mass", H5P_DEFAULT) : H5I_INVALID_HID, H5Dclose);
    const Handle space(set.ok() ? H5Dget_space(set.get()) : H5I_INVALID_HID, H5Sclose);
    hsize_t count = 0;
    if (!space.ok() || !read_attribute(g.get(), "time", H5T_NATIVE_DOUBLE, header.time) ||
        H5Sget_simple_extent_dims(space.get(), &count, nullptr) != 1) {
      throw std::runtime_error("cannot read frame /frames/" + names[i] + " from HDF5 file " +
                               quoted(h5_path));
    }
    header.count = count;
    im.append_grid(header, names[i]);
  }
  im.frames = keep_frames;
  if (H5Fflush(im.file.get(), H5F_SCOPE_GLOBAL) < 0) {
    throw std::runtime_error("cannot write HDF5 file " + quoted(h5_path));
  }
  im.write_xmf();
}

ParticleWriter::~ParticleWriter() = default;

void ParticleWriter::write(const ParticleFrame& frame) {
  check_sizes(frame);
  silence_hdf5();
  Impl& im = *impl_;
  const std::string group = frame_name(im.frames);
  try {
    im.write_frame(frame, group);
  } catch (...) {
    // Drop the partial group so a retry can reuse the name and readers never see half a frame.
    H5Ldelete(im.file.get(), ("/frames/" + group).c_str(), H5P_DEFAULT);
    throw;
  }
  if (H5Fflush(im.file.get(), H5F_SCOPE_GLOBAL) < 0) {
    throw std::runtime_error("cannot flush HDF5 file " + quoted(im.h5_path));
  }
  ++im.frames;
  im.append_grid(frame, group);
  im.write_xmf();
}

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
    throw std::runtime_error("cannot read frame /frames/" + names[index] + " from HDF5 file " +
                             quoted(h5_path));
  }
  frame.count = counts[0];
  return frame;
}

std::size_t count_frames(const std::filesystem::path& h5_path) {
  const Handle file = open_for_reading(h5_path);
  return frame_names(file.get(), h5_path).size();
}

}  // namespace mpm
