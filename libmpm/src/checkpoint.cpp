#include "mpm/checkpoint.hpp"

#include <filesystem>
#include <stdexcept>
#include <system_error>

#include "hdf5_util.hpp"
#include "sync_file.hpp"

namespace mpm {
namespace {

using namespace detail;  // NOLINT(google-build-using-namespace): HDF5 helpers

template <class Map>
const typename Map::mapped_type& lookup(const Map& map, const std::string& key, std::size_t size) {
  const auto it = map.find(key);
  if (it == map.end()) throw std::runtime_error("checkpoint has no '" + key + "'");
  if constexpr (!std::is_same_v<typename Map::mapped_type, std::string>) {
    if (size > 0 && it->second.size() != size) {
      throw std::runtime_error("checkpoint '" + key + "' holds " +
                               std::to_string(it->second.size()) + " values, expected " +
                               std::to_string(size));
    }
  }
  return it->second;
}

}  // namespace

const std::vector<double>& Checkpoint::real(const std::string& key, std::size_t size) const {
  return lookup(reals, key, size);
}
const std::vector<std::int64_t>& Checkpoint::integer(const std::string& key,
                                                     std::size_t size) const {
  return lookup(integers, key, size);
}
const std::string& Checkpoint::text(const std::string& key) const { return lookup(texts, key, 0); }

void write_checkpoint(const std::filesystem::path& file, const Checkpoint& checkpoint) {
  silence_hdf5();
  const auto write = [&](const std::filesystem::path& tmp) {
    const Handle h5(H5Fcreate(tmp.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT), H5Fclose);
    if (!h5.ok()) return false;
    const Handle reals(H5Gcreate2(h5.get(), "reals", H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT),
                       H5Gclose);
    const Handle ints(H5Gcreate2(h5.get(), "integers", H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT),
                      H5Gclose);
    const Handle texts(H5Gcreate2(h5.get(), "texts", H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT),
                       H5Gclose);
    bool good = reals.ok() && ints.ok() && texts.ok();
    for (const auto& [key, values] : checkpoint.reals) {
      good = good && write_dataset(reals.get(), key.c_str(), H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE,
                                   values.data(), values.size(), 1);
    }
    for (const auto& [key, values] : checkpoint.integers) {
      good = good && write_dataset(ints.get(), key.c_str(), H5T_STD_I64LE, H5T_NATIVE_INT64,
                                   values.data(), values.size(), 1);
    }
    for (const auto& [key, value] : checkpoint.texts) {
      good = good && write_dataset(texts.get(), key.c_str(), H5T_STD_I8LE, H5T_NATIVE_CHAR,
                                   value.data(), value.size(), 1);
    }
    return good && H5Fflush(h5.get(), H5F_SCOPE_GLOBAL) >= 0;
  };
  // On the disk before it takes the checkpoint's name, and the name on the disk after.
  if (!replace_file(file, write, true)) {
    throw std::runtime_error("cannot write checkpoint " + quoted(file));
  }
}

Checkpoint read_checkpoint(const std::filesystem::path& file, bool texts_only) {
  silence_hdf5();
  const auto fail = [&](const std::string& what) {
    return std::runtime_error("cannot read checkpoint " + quoted(file) + ": " + what);
  };
  std::error_code error;
  if (!std::filesystem::exists(file, error)) throw fail("no such file (nothing to resume)");
  const Handle h5(H5Fopen(file.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT), H5Fclose);
  if (!h5.ok()) throw fail("not an HDF5 file");
  Checkpoint c;
  const Handle reals(H5Gopen2(h5.get(), "reals", H5P_DEFAULT), H5Gclose);
  const Handle ints(H5Gopen2(h5.get(), "integers", H5P_DEFAULT), H5Gclose);
  const Handle texts(H5Gopen2(h5.get(), "texts", H5P_DEFAULT), H5Gclose);
  if (!reals.ok() || !ints.ok() || !texts.ok()) throw fail("not a checkpoint");
  std::size_t count = 0;
  std::vector<std::string> keys;
  const auto list = [&](const Handle& group) {
    if (!link_names(group.get(), keys)) throw fail("cannot list its contents");
    return keys;
  };
  for (const std::string& key : list(texts)) {
    std::vector<char> chars;
    if (!read_dataset(texts.get(), key.c_str(), H5T_NATIVE_CHAR, 1, count, chars)) {
      throw fail(key);
    }
    c.texts[key] = std::string(chars.begin(), chars.end());
  }
  if (texts_only) return c;
  for (const std::string& key : list(reals)) {
    if (!read_dataset(reals.get(), key.c_str(), H5T_NATIVE_DOUBLE, 1, count, c.reals[key])) {
      throw fail(key);
    }
  }
  for (const std::string& key : list(ints)) {
    if (!read_dataset(ints.get(), key.c_str(), H5T_NATIVE_INT64, 1, count, c.integers[key])) {
      throw fail(key);
    }
  }
  return c;
}

}  // namespace mpm
