#pragma once
// HDF5 and XDMF helpers shared by the particle output and the boundary package (internal to
// libmpm: HDF5 never appears in a public header).

#include <hdf5.h>

#include <array>
#include <charconv>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

namespace mpm::detail {

inline std::string quoted(const std::filesystem::path& path) { return "'" + path.string() + "'"; }

// Owns one HDF5 identifier so every early return and exception closes it.
class Handle {
 public:
  Handle(hid_t id, herr_t (*closer)(hid_t)) : id_(id), close_(closer) {}
  Handle(Handle&& other) noexcept
      : id_(std::exchange(other.id_, H5I_INVALID_HID)), close_(other.close_) {}
  Handle& operator=(Handle&& other) noexcept {
    std::swap(id_, other.id_);  // our old id is closed when `other` goes away
    std::swap(close_, other.close_);
    return *this;
  }
  ~Handle() {
    if (id_ >= 0) close_(id_);
  }
  [[nodiscard]] hid_t get() const { return id_; }
  [[nodiscard]] bool ok() const { return id_ >= 0; }
  /// Closes now and reports whether that worked (closing a file writes what HDF5 still holds).
  bool close() {
    const hid_t id = std::exchange(id_, H5I_INVALID_HID);
    return id < 0 || close_(id) >= 0;
  }

 private:
  hid_t id_;
  herr_t (*close_)(hid_t);
};

// HDF5 prints an error stack to stderr by default; our exceptions carry the one line users need.
inline void silence_hdf5() { H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr); }

// Shortest text that parses back to the same double, so the XDMF time matches the HDF5 one.
inline std::string format_double(double value) {
  std::array<char, 32> buf{};
  const auto result = std::to_chars(buf.data(), buf.data() + buf.size(), value);
  return {buf.data(), result.ptr};
}

inline std::string xml_escape(const std::string& text) {
  std::string out;
  for (const char c : text) {
    if (c == '&')
      out += "&amp;";
    else if (c == '<')
      out += "&lt;";
    else if (c == '>')
      out += "&gt;";
    else if (c == '"')
      out += "&quot;";
    else
      out += c;
  }
  return out;
}

inline bool write_dataset(hid_t group, const char* name, hid_t file_type, hid_t mem_type,
                          const void* data, std::size_t count, std::size_t components) {
  const std::array<hsize_t, 2> dims{count, components};
  const Handle space(H5Screate_simple(components == 1 ? 1 : 2, dims.data(), nullptr), H5Sclose);
  if (!space.ok()) return false;
  // No modification times in the object headers (HDF5 records them by default): the same data
  // make the same file, so two runs' outputs compare byte for byte.
  const Handle create(H5Pcreate(H5P_DATASET_CREATE), H5Pclose);
  if (!create.ok() || H5Pset_obj_track_times(create.get(), 0) < 0) return false;
  const Handle set(
      H5Dcreate2(group, name, file_type, space.get(), H5P_DEFAULT, create.get(), H5P_DEFAULT),
      H5Dclose);
  if (!set.ok()) return false;
  // An empty vector may have a null data(); HDF5 rejects a null buffer, and there is nothing to
  // write anyway.
  return count == 0 || H5Dwrite(set.get(), mem_type, H5S_ALL, H5S_ALL, H5P_DEFAULT, data) >= 0;
}

template <typename T>
bool write_attribute(hid_t group, const char* name, hid_t file_type, hid_t mem_type, T value) {
  const Handle space(H5Screate(H5S_SCALAR), H5Sclose);
  if (!space.ok()) return false;
  const Handle attr(H5Acreate2(group, name, file_type, space.get(), H5P_DEFAULT, H5P_DEFAULT),
                    H5Aclose);
  return attr.ok() && H5Awrite(attr.get(), mem_type, &value) >= 0;
}

// Reads a (count) or (count x components) dataset. Returns false rather than throwing so the
// caller, which knows the file name, builds the message.
template <typename T>
bool read_dataset(hid_t group, const char* name, hid_t mem_type, std::size_t components,
                  std::size_t& count, std::vector<T>& out) {
  const Handle set(H5Dopen2(group, name, H5P_DEFAULT), H5Dclose);
  if (!set.ok()) return false;
  const Handle space(H5Dget_space(set.get()), H5Sclose);
  if (!space.ok()) return false;
  const int rank = H5Sget_simple_extent_ndims(space.get());
  std::array<hsize_t, 2> dims{0, 1};
  if (rank != (components == 1 ? 1 : 2) ||
      H5Sget_simple_extent_dims(space.get(), dims.data(), nullptr) != rank) {
    return false;
  }
  if (dims[1] != components) return false;
  count = dims[0];
  out.resize(count * components);
  return count == 0 || H5Dread(set.get(), mem_type, H5S_ALL, H5S_ALL, H5P_DEFAULT, out.data()) >= 0;
}

// The names of the links in a group, in the name index's order. Returns false if the group
// cannot be listed (the caller, which knows the file name, builds the message).
inline bool link_names(hid_t group, std::vector<std::string>& names) {
  H5G_info_t info{};
  if (H5Gget_info(group, &info) < 0) return false;
  names.clear();
  for (hsize_t i = 0; i < info.nlinks; ++i) {
    const ssize_t size =
        H5Lget_name_by_idx(group, ".", H5_INDEX_NAME, H5_ITER_INC, i, nullptr, 0, H5P_DEFAULT);
    if (size < 0) return false;
    std::string name(static_cast<std::size_t>(size) + 1, '\0');
    H5Lget_name_by_idx(group, ".", H5_INDEX_NAME, H5_ITER_INC, i, name.data(), name.size(),
                       H5P_DEFAULT);
    name.resize(static_cast<std::size_t>(size));
    names.push_back(std::move(name));
  }
  return true;
}

template <typename T>
bool read_attribute(hid_t group, const char* name, hid_t mem_type, T& value) {
  const Handle attr(H5Aopen(group, name, H5P_DEFAULT), H5Aclose);
  return attr.ok() && H5Aread(attr.get(), mem_type, &value) >= 0;
}

}  // namespace mpm::detail
