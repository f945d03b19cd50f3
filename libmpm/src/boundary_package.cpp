// The boundary package: build (prepare_boundary), store and load (HDF5 + XDMF).

#include "mpm/boundary_package.hpp"

#include <cmath>
#include <cstdio>
#include <exception>
#include <fstream>
#include <sstream>
#include <stdexcept>

#include <Eigen/SparseCore>

#include "hdf5_util.hpp"
#include "mpm/grid.hpp"
#include "sync_file.hpp"

namespace mpm {
namespace {

using namespace detail;  // NOLINT(google-build-using-namespace): HDF5 helpers

constexpr int kFormatVersion = 1;

using RowMatrixXd = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using RowMatrixXi = Eigen::Matrix<int, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

[[noreturn]] void fail(const std::filesystem::path& file, const std::string& what) {
  throw std::runtime_error("boundary package " + quoted(file) + ": " + what);
}

// --- writing -------------------------------------------------------------------------------

class Writer {
 public:
  explicit Writer(const std::filesystem::path& file) : file_(file) {
    silence_hdf5();
    handle_ = Handle(H5Fcreate(file.c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT), H5Fclose);
    if (!handle_.ok()) fail(file, "cannot create the file");
  }
  Handle group(const std::string& path) {
    Handle g(H5Gcreate2(handle_.get(), path.c_str(), H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT),
             H5Gclose);
    if (!g.ok()) fail(file_, "cannot create group " + path);
    return g;
  }
  void matrix(hid_t where, const char* name, const Eigen::MatrixXd& m) {
    const RowMatrixXd rows = m;
    check(write_dataset(where, name, H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, rows.data(),
                        static_cast<std::size_t>(m.rows()), static_cast<std::size_t>(m.cols())),
          name);
  }
  void matrix(hid_t where, const char* name, const Eigen::MatrixXi& m) {
    const RowMatrixXi rows = m;
    check(write_dataset(where, name, H5T_STD_I32LE, H5T_NATIVE_INT, rows.data(),
                        static_cast<std::size_t>(m.rows()), static_cast<std::size_t>(m.cols())),
          name);
  }
  template <class T>
  void vector(hid_t where, const char* name, const std::vector<T>& v) {
    if constexpr (std::is_same_v<T, double>) {
      check(write_dataset(where, name, H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, v.data(), v.size(), 1),
            name);
    } else if constexpr (std::is_same_v<T, std::uint8_t>) {
      check(write_dataset(where, name, H5T_STD_U8LE, H5T_NATIVE_UINT8, v.data(), v.size(), 1),
            name);
    } else {
      check(write_dataset(where, name, H5T_STD_I32LE, H5T_NATIVE_INT, v.data(), v.size(), 1), name);
    }
  }
  void number(hid_t where, const char* name, double value) {
    check(write_attribute(where, name, H5T_IEEE_F64LE, H5T_NATIVE_DOUBLE, value), name);
  }
  void integer(hid_t where, const char* name, long long value) {
    check(write_attribute(where, name, H5T_STD_I64LE, H5T_NATIVE_LLONG, value), name);
  }
  void text(hid_t where, const char* name, const std::string& value) {
    const Handle type(H5Tcopy(H5T_C_S1), H5Tclose);
    H5Tset_size(type.get(), std::max<std::size_t>(1, value.size()));
    const Handle space(H5Screate(H5S_SCALAR), H5Sclose);
    const Handle attr(H5Acreate2(where, name, type.get(), space.get(), H5P_DEFAULT, H5P_DEFAULT),
                      H5Aclose);
    const std::string padded = value.empty() ? std::string(1, '\0') : value;
    check(attr.ok() && H5Awrite(attr.get(), type.get(), padded.data()) >= 0, name);
  }
  void strings(hid_t where, const char* name, const std::vector<std::string>& values) {
    const Handle type(H5Tcopy(H5T_C_S1), H5Tclose);
    H5Tset_size(type.get(), H5T_VARIABLE);
    std::vector<const char*> pointers;
    for (const auto& v : values) pointers.push_back(v.c_str());
    check(write_dataset(where, name, type.get(), type.get(), pointers.data(), pointers.size(), 1),
          name);
  }
  void sparse(hid_t where, const char* prefix, const Eigen::SparseMatrix<double>& m) {
    std::vector<int> rows, cols;
    std::vector<double> values;
    for (int k = 0; k < m.outerSize(); ++k) {
      for (Eigen::SparseMatrix<double>::InnerIterator it(m, k); it; ++it) {
        rows.push_back(static_cast<int>(it.row()));
        cols.push_back(static_cast<int>(it.col()));
        values.push_back(it.value());
      }
    }
    const std::string p(prefix);
    vector(where, (p + "_rows").c_str(), rows);
    vector(where, (p + "_cols").c_str(), cols);
    vector(where, (p + "_values").c_str(), values);
    integer(where, (p + "_row_count").c_str(), m.rows());
    integer(where, (p + "_col_count").c_str(), m.cols());
  }
  [[nodiscard]] hid_t root() const { return handle_.get(); }
  void flush() {
    if (H5Fflush(handle_.get(), H5F_SCOPE_GLOBAL) < 0) fail(file_, "cannot flush");
  }

 private:
  void check(bool ok, const char* what) const {
    if (!ok) fail(file_, std::string("cannot write ") + what);
  }
  std::filesystem::path file_;
  Handle handle_{H5I_INVALID_HID, H5Fclose};
};

void write_coupling(Writer& w, hid_t group, const mpmgeom::Coupling& c) {
  w.vector(group, "multiplier_node", c.multiplier_node);
  std::vector<double> integral(c.multiplier_integral.data(),
                               c.multiplier_integral.data() + c.multiplier_integral.size());
  w.vector(group, "multiplier_integral", integral);
  w.sparse(group, "grid", c.grid);
  w.sparse(group, "boundary", c.boundary);
}

const char* kernel_name(mpmgeom::GridSpec::Kernel k) {
  return k == mpmgeom::GridSpec::Kernel::linear ? "linear" : "bspline2";
}

/// Points padded to 3D and cells in VTK/XDMF node order, for ParaView.
void write_visualisation(Writer& w, const mpmgeom::BoundaryGrid& layer) {
  const Handle g = w.group("/xdmf");
  Eigen::MatrixXd points = Eigen::MatrixXd::Zero(layer.nodes.rows(), 3);
  points.leftCols(layer.dimension) = layer.nodes;
  w.matrix(g.get(), "points", points);
  Eigen::MatrixXi cells = layer.cells;
  if (layer.dimension == 3) {
    // VTK wedge: base (0,1,2) wound with its normal pointing away from (3,4,5); our wall
    // triangle faces the material, so reverse both triangles.
    cells.col(1) = layer.cells.col(2);
    cells.col(2) = layer.cells.col(1);
    cells.col(4) = layer.cells.col(5);
    cells.col(5) = layer.cells.col(4);
  } else if (layer.dimension == 2) {
    cells.col(2) = layer.cells.col(3);  // quads go round: w0 w1 i1 i0
    cells.col(3) = layer.cells.col(2);
  }
  w.matrix(g.get(), "cells", cells);
}

std::string xdmf_text(const mpmgeom::BoundaryGrid& layer, const std::string& h5_name) {
  const auto n = layer.nodes.rows();
  const auto c = layer.cells.rows();
  const char* topology = layer.dimension == 3   ? "Wedge"
                         : layer.dimension == 2 ? "Quadrilateral"
                                                : "Polyline";
  const char* facet_topology = layer.dimension == 3   ? "Triangle"
                               : layer.dimension == 2 ? "Polyline"
                                                      : "Polyvertex";
  const std::string file = xml_escape(h5_name);
  std::ostringstream x;
  auto item = [&](const std::string& path, long rows, long cols, const char* type) {
    x << "        <DataItem Format=\"HDF\" NumberType=\"" << type << "\" Precision=\""
      << (std::string(type) == "Float" ? 8 : 4) << "\" Dimensions=\"" << rows;
    if (cols > 1) x << " " << cols;
    x << "\">" << file << ":" << path << "</DataItem>\n";
  };
  x << "<?xml version=\"1.0\" ?>\n<Xdmf Version=\"3.0\">\n  <Domain>\n";
  x << "    <Grid Name=\"layer\" GridType=\"Uniform\">\n";
  x << "      <Topology TopologyType=\"" << topology << "\" NumberOfElements=\"" << c << "\""
    << (layer.dimension == 1 ? " NodesPerElement=\"2\"" : "") << ">\n";
  item("/xdmf/cells", c, layer.nodes_per_cell(), "Int");
  x << "      </Topology>\n      <Geometry GeometryType=\"XYZ\">\n";
  item("/xdmf/points", n, 3, "Float");
  x << "      </Geometry>\n";
  x << "      <Attribute Name=\"part\" AttributeType=\"Scalar\" Center=\"Cell\">\n";
  item("/layer/cell_part", c, 1, "Int");
  x << "      </Attribute>\n      <Attribute Name=\"sub_layer\" AttributeType=\"Scalar\" "
       "Center=\"Cell\">\n";
  item("/layer/cell_layer", c, 1, "Int");
  x << "      </Attribute>\n      <Attribute Name=\"on_wall\" AttributeType=\"Scalar\" "
       "Center=\"Node\">\n";
  item("/layer/node_on_wall", n, 1, "Int");
  x << "      </Attribute>\n    </Grid>\n";
  const std::pair<const char*, const Eigen::MatrixXi*> facets[] = {
      {"wall", &layer.wall_facets}, {"interface", &layer.interface_facets}};
  for (const auto& [name, f] : facets) {
    x << "    <Grid Name=\"" << name << "\" GridType=\"Uniform\">\n";
    x << "      <Topology TopologyType=\"" << facet_topology << "\" NumberOfElements=\""
      << f->rows() << "\"" << (layer.dimension == 2 ? " NodesPerElement=\"2\"" : "") << ">\n";
    item(std::string("/layer/") + name + "_facets", f->rows(), f->cols(), "Int");
    x << "      </Topology>\n      <Geometry GeometryType=\"XYZ\">\n";
    item("/xdmf/points", n, 3, "Float");
    x << "      </Geometry>\n    </Grid>\n";
  }
  x << "  </Domain>\n</Xdmf>\n";
  return x.str();
}

// --- reading -------------------------------------------------------------------------------

class Reader {
 public:
  explicit Reader(const std::filesystem::path& file) : file_(file) {
    silence_hdf5();
    std::error_code ec;
    if (!std::filesystem::is_regular_file(file, ec)) fail(file, "file does not exist");
    handle_ = Handle(H5Fopen(file.c_str(), H5F_ACC_RDONLY, H5P_DEFAULT), H5Fclose);
    if (!handle_.ok()) fail(file, "not an HDF5 file");
  }
  Handle group(const std::string& path) const {
    Handle g(H5Gopen2(handle_.get(), path.c_str(), H5P_DEFAULT), H5Gclose);
    if (!g.ok()) fail(file_, "missing group " + path);
    return g;
  }
  template <class T>
  std::vector<T> vector(hid_t where, const char* name, std::size_t components = 1) const {
    std::vector<T> out;
    std::size_t count = 0;
    bool ok;
    if constexpr (std::is_same_v<T, double>) {
      ok = read_dataset(where, name, H5T_NATIVE_DOUBLE, components, count, out);
    } else if constexpr (std::is_same_v<T, std::uint8_t>) {
      ok = read_dataset(where, name, H5T_NATIVE_UINT8, components, count, out);
    } else {
      ok = read_dataset(where, name, H5T_NATIVE_INT, components, count, out);
    }
    if (!ok) fail(file_, std::string("missing or malformed dataset ") + name);
    return out;
  }
  Eigen::MatrixXd matrix_d(hid_t where, const char* name, int cols) const {
    const auto v = vector<double>(where, name, static_cast<std::size_t>(cols));
    return Eigen::Map<const RowMatrixXd>(v.data(), static_cast<Eigen::Index>(v.size() / cols),
                                         cols);
  }
  Eigen::MatrixXi matrix_i(hid_t where, const char* name, int cols) const {
    const auto v = vector<int>(where, name, static_cast<std::size_t>(cols));
    return Eigen::Map<const RowMatrixXi>(v.data(), static_cast<Eigen::Index>(v.size() / cols),
                                         cols);
  }
  double number(hid_t where, const char* name) const {
    double value = 0;
    if (!read_attribute(where, name, H5T_NATIVE_DOUBLE, value)) fail(file_, missing(name));
    return value;
  }
  long long integer(hid_t where, const char* name) const {
    long long value = 0;
    if (!read_attribute(where, name, H5T_NATIVE_LLONG, value)) fail(file_, missing(name));
    return value;
  }
  std::string text(hid_t where, const char* name) const {
    const Handle attr(H5Aopen(where, name, H5P_DEFAULT), H5Aclose);
    if (!attr.ok()) fail(file_, missing(name));
    const Handle type(H5Aget_type(attr.get()), H5Tclose);
    std::string value(H5Tget_size(type.get()), '\0');
    if (H5Aread(attr.get(), type.get(), value.data()) < 0) fail(file_, missing(name));
    return value.substr(0, value.find('\0'));
  }
  std::vector<std::string> strings(hid_t where, const char* name) const {
    const Handle set(H5Dopen2(where, name, H5P_DEFAULT), H5Dclose);
    if (!set.ok()) fail(file_, missing(name));
    const Handle space(H5Dget_space(set.get()), H5Sclose);
    const auto count = static_cast<std::size_t>(H5Sget_simple_extent_npoints(space.get()));
    const Handle type(H5Tcopy(H5T_C_S1), H5Tclose);
    H5Tset_size(type.get(), H5T_VARIABLE);
    std::vector<char*> raw(count, nullptr);
    if (count > 0 &&
        H5Dread(set.get(), type.get(), H5S_ALL, H5S_ALL, H5P_DEFAULT, raw.data()) < 0) {
      fail(file_, missing(name));
    }
    std::vector<std::string> out(raw.begin(), raw.end());
    if (count > 0) H5Dvlen_reclaim(type.get(), space.get(), H5P_DEFAULT, raw.data());
    return out;
  }
  Eigen::SparseMatrix<double> sparse(hid_t where, const std::string& prefix) const {
    const auto rows = vector<int>(where, (prefix + "_rows").c_str());
    const auto cols = vector<int>(where, (prefix + "_cols").c_str());
    const auto values = vector<double>(where, (prefix + "_values").c_str());
    const auto n_rows = integer(where, (prefix + "_row_count").c_str());
    const auto n_cols = integer(where, (prefix + "_col_count").c_str());
    if (rows.size() != values.size() || cols.size() != values.size()) {
      fail(file_, "inconsistent sparse matrix " + prefix);
    }
    std::vector<Eigen::Triplet<double>> triplets;
    triplets.reserve(values.size());
    for (std::size_t k = 0; k < values.size(); ++k) {
      if (rows[k] < 0 || rows[k] >= n_rows || cols[k] < 0 || cols[k] >= n_cols) {
        fail(file_, "index out of range in sparse matrix " + prefix);
      }
      triplets.emplace_back(rows[k], cols[k], values[k]);
    }
    Eigen::SparseMatrix<double> m(n_rows, n_cols);
    m.setFromTriplets(triplets.begin(), triplets.end());
    return m;
  }
  [[nodiscard]] hid_t root() const { return handle_.get(); }

 private:
  static std::string missing(const char* name) {
    return std::string("missing or malformed '") + name + "'";
  }
  std::filesystem::path file_;
  Handle handle_{H5I_INVALID_HID, H5Fclose};
};

mpmgeom::Coupling read_coupling(const Reader& r, hid_t group) {
  mpmgeom::Coupling c;
  c.multiplier_node = r.vector<int>(group, "multiplier_node");
  const auto integral = r.vector<double>(group, "multiplier_integral");
  c.multiplier_integral = Eigen::Map<const Eigen::VectorXd>(
      integral.data(), static_cast<Eigen::Index>(integral.size()));
  c.grid = r.sparse(group, "grid");
  c.boundary = r.sparse(group, "boundary");
  return c;
}

std::uint64_t fnv1a(std::uint64_t hash, const void* data, std::size_t size) {
  const auto* bytes = static_cast<const unsigned char*>(data);
  for (std::size_t i = 0; i < size; ++i) {
    hash ^= bytes[i];
    hash *= 1099511628211ULL;
  }
  return hash;
}

}  // namespace

mpmgeom::GridSpec standard_grid_spec(int dimension, const Eigen::VectorXd& box_min,
                                     const Eigen::VectorXd& box_max, double spacing,
                                     ShapeKind shape) {
  constexpr int pad = kGhostLayers;
  mpmgeom::GridSpec g;
  g.dimension = dimension;
  g.spacing = spacing;
  g.kernel = shape == ShapeKind::bspline2 ? mpmgeom::GridSpec::Kernel::bspline2
                                          : mpmgeom::GridSpec::Kernel::linear;
  for (int d = 0; d < dimension; ++d) {
    const auto cells = static_cast<int>(std::lround((box_max[d] - box_min[d]) / spacing));
    g.origin[d] = box_min[d] - pad * spacing;
    g.nodes[d] = cells + 1 + 2 * pad;
  }
  return g;
}

std::string boundary_digest(const std::filesystem::path& mesh_file, const PrepOptions& o,
                            const mpmgeom::GridSpec& g) {
  std::uint64_t hash = 1469598103934665603ULL;
  std::ifstream in(mesh_file, std::ios::binary);
  std::vector<char> buffer(1 << 16);
  while (in.read(buffer.data(), static_cast<std::streamsize>(buffer.size())) || in.gcount() > 0) {
    hash = fnv1a(hash, buffer.data(), static_cast<std::size_t>(in.gcount()));
  }
  std::ostringstream opts;
  opts.precision(17);
  opts << o.import.scale << ' ' << o.import.translation.transpose() << ' '
       << o.import.rotation_deg.transpose() << ' ' << o.import.weld_tolerance << ' '
       << o.repair.require_closed << o.repair.reject_self_intersections << ' ' << o.remesh << ' '
       << o.remesh_factor << ' ' << o.layer.thickness << ' ' << o.layer.layers << ' '
       << o.layer.normal_smoothing << ' ' << o.layer.min_thickness_fraction << ' ' << g.dimension
       << ' ' << g.origin.transpose() << ' ' << g.spacing << ' ' << g.nodes.transpose() << ' '
       << kernel_name(g.kernel);
  const std::string text = opts.str();
  hash = fnv1a(hash, text.data(), text.size());
  char hex[17];
  std::snprintf(hex, sizeof hex, "%016llx", static_cast<unsigned long long>(hash));
  return hex;
}

BoundaryPackage prepare_boundary(const std::filesystem::path& mesh_file, const PrepOptions& options,
                                 const mpmgeom::GridSpec& grid) {
  return prepare_boundary(mpmgeom::load_mesh(mesh_file, options.import), mesh_file, options, grid);
}

BoundaryPackage prepare_boundary(const mpmgeom::TriangleMesh& imported,
                                 const std::filesystem::path& mesh_file, const PrepOptions& options,
                                 const mpmgeom::GridSpec& grid) {
  std::string why;
  if (!options.layer.valid(&why)) throw std::invalid_argument(why);
  // A terrain may reach past the grid, but not by orders of magnitude (units).
  Eigen::Vector3d extent = Eigen::Vector3d::Zero();
  for (int d = 0; d < grid.dimension; ++d) extent[d] = (grid.nodes[d] - 1) * grid.spacing;
  mpmgeom::check_extent(imported, mesh_file.string(), extent.norm());
  BoundaryPackage package;
  mpmgeom::TriangleMesh mesh =
      mpmgeom::validate_and_repair(imported, mesh_file.string(), options.repair, &package.repairs);
  if (options.remesh) {
    // Remeshing and the layer cost memory per triangle (about 1 kB in CGAL's remesher): refuse
    // what would not fit in a workstation's memory rather than be killed by it.
    const double edge = options.remesh_factor * grid.spacing;
    const double area = mpmgeom::surface_area(mesh);
    const double triangles = area / (std::sqrt(3.0) / 4.0 * edge * edge);
    constexpr double kMaxTriangles = 5e6;
    if (triangles > kMaxTriangles) {
      std::ostringstream text;
      text << "mesh '" << mesh_file.string() << "': remeshing its area " << area
           << " at edge length " << edge << " would make about " << triangles
           << " triangles (at most " << kMaxTriangles
           << "); coordinates in other units, or a finer spacing than meant?";
      throw mpmgeom::MeshError(text.str());
    }
    mesh = mpmgeom::remesh_isotropic(mesh, edge);
  }
  package.layer = mpmgeom::extrude_layer(mesh, options.layer, &package.report);
  package.grid = grid;
  package.interface_coupling =
      mpmgeom::couple(package.layer, grid, mpmgeom::CouplingSurface::interface);
  package.wall_coupling = mpmgeom::couple(package.layer, grid, mpmgeom::CouplingSurface::wall);
  package.cell_flags = mpmgeom::layer_cell_flags(package.layer, grid);
  package.source = mesh_file.string();
  package.source_digest = boundary_digest(mesh_file, options, grid);
  return package;
}

namespace {

// Writes the package's HDF5 file at `path` (save_boundary_package() passes a temporary name).
void write_package(const BoundaryPackage& p, const std::filesystem::path& path) {
  {
    Writer w(path);
    const hid_t root = w.root();
    w.text(root, "format", "mpm-boundary-package");
    w.integer(root, "version", kFormatVersion);
    w.text(root, "source", p.source);
    w.text(root, "source_digest", p.source_digest);

    const Handle grid = w.group("/grid");
    w.integer(grid.get(), "dimension", p.grid.dimension);
    for (int d = 0; d < 3; ++d) {
      const std::string axis = std::to_string(d);
      w.number(grid.get(), ("origin_" + axis).c_str(), p.grid.origin[d]);
      w.integer(grid.get(), ("nodes_" + axis).c_str(), p.grid.nodes[d]);
    }
    w.number(grid.get(), "spacing", p.grid.spacing);
    w.text(grid.get(), "kernel", kernel_name(p.grid.kernel));

    const mpmgeom::BoundaryGrid& l = p.layer;
    const Handle layer = w.group("/layer");
    w.integer(layer.get(), "dimension", l.dimension);
    w.integer(layer.get(), "layers", l.layers);
    w.number(layer.get(), "thickness", l.thickness);
    w.matrix(layer.get(), "nodes", l.nodes);
    w.matrix(layer.get(), "cells", l.cells);
    w.matrix(layer.get(), "cell_layer", Eigen::MatrixXi(l.cell_layer));
    w.matrix(layer.get(), "cell_part", Eigen::MatrixXi(l.cell_part));
    w.strings(layer.get(), "part_names", l.part_names);
    w.matrix(layer.get(), "wall_facets", l.wall_facets);
    w.matrix(layer.get(), "interface_facets", l.interface_facets);
    w.matrix(layer.get(), "wall_facet_part", Eigen::MatrixXi(l.wall_facet_part));
    w.matrix(layer.get(), "node_normals", l.node_normals);
    w.matrix(layer.get(), "node_on_wall", Eigen::MatrixXi(l.node_on_wall));
    w.matrix(layer.get(), "node_on_interface", Eigen::MatrixXi(l.node_on_interface));

    w.group("/coupling");
    const Handle phi = w.group("/coupling/interface");
    write_coupling(w, phi.get(), p.interface_coupling);
    const Handle gamma = w.group("/coupling/wall");
    write_coupling(w, gamma.get(), p.wall_coupling);
    w.vector(root, "cell_flags", p.cell_flags);

    const Handle report = w.group("/report");
    w.integer(report.get(), "cells", static_cast<long long>(p.report.cells));
    w.integer(report.get(), "nodes", static_cast<long long>(p.report.nodes));
    w.integer(report.get(), "columns_shrunk", static_cast<long long>(p.report.columns_shrunk));
    w.integer(report.get(), "crease_normals", static_cast<long long>(p.report.crease_normals));
    w.number(report.get(), "max_shrink", p.report.max_shrink);
    w.number(report.get(), "min_jacobian", p.report.min_jacobian);
    w.number(report.get(), "volume", p.report.volume);
    w.number(report.get(), "wall_measure", p.report.wall_measure);
    w.number(report.get(), "interface_measure", p.report.interface_measure);

    write_visualisation(w, l);
    w.flush();
  }
}

// replace_file() with a writer that throws: its exception is carried out (the temporary file
// removed), and a failure to put the file in place names the file.
template <class Write>
void replace_or_throw(const std::filesystem::path& file, Write&& write) {
  std::exception_ptr error;
  const bool replaced = detail::replace_file(
      file,
      [&](const std::filesystem::path& tmp) {
        try {
          write(tmp);
          return true;
        } catch (...) {
          error = std::current_exception();
          return false;
        }
      },
      true);
  if (error) std::rethrow_exception(error);
  if (!replaced) fail(file, "cannot put the written file in place (sync or rename failed)");
}

}  // namespace

// Each file is written aside and renamed over the old one once it is on the disk: a kill, a
// power cut or a write error leaves the old package or the new one, never a part of one (`mpm
// prep` output, the scene cache, a run's wall geometry).
void save_boundary_package(const BoundaryPackage& p, const std::filesystem::path& h5_path,
                           const std::filesystem::path& xmf_path) {
  replace_or_throw(h5_path, [&](const std::filesystem::path& tmp) { write_package(p, tmp); });
  replace_or_throw(xmf_path, [&](const std::filesystem::path& tmp) {
    std::ofstream out(tmp);
    out << xdmf_text(p.layer,
                     std::filesystem::relative(
                         h5_path, xmf_path.parent_path().empty() ? "." : xmf_path.parent_path())
                         .string());
    if (!out.flush()) fail(xmf_path, "cannot write the XDMF index");
  });
}

BoundaryPackage load_boundary_package(const std::filesystem::path& h5_path) {
  const Reader r(h5_path);
  const hid_t root = r.root();
  if (r.text(root, "format") != "mpm-boundary-package") fail(h5_path, "not a boundary package");
  const auto version = r.integer(root, "version");
  if (version != kFormatVersion) {
    fail(h5_path, "format version " + std::to_string(version) + " (this program reads " +
                      std::to_string(kFormatVersion) + "); run `mpm prep` again");
  }
  BoundaryPackage p;
  p.source = r.text(root, "source");
  p.source_digest = r.text(root, "source_digest");

  const Handle grid = r.group("/grid");
  p.grid.dimension = static_cast<int>(r.integer(grid.get(), "dimension"));
  for (int d = 0; d < 3; ++d) {
    const std::string axis = std::to_string(d);
    p.grid.origin[d] = r.number(grid.get(), ("origin_" + axis).c_str());
    p.grid.nodes[d] = static_cast<int>(r.integer(grid.get(), ("nodes_" + axis).c_str()));
  }
  p.grid.spacing = r.number(grid.get(), "spacing");
  p.grid.kernel = r.text(grid.get(), "kernel") == "linear" ? mpmgeom::GridSpec::Kernel::linear
                                                           : mpmgeom::GridSpec::Kernel::bspline2;

  mpmgeom::BoundaryGrid& l = p.layer;
  const Handle layer = r.group("/layer");
  l.dimension = static_cast<int>(r.integer(layer.get(), "dimension"));
  if (l.dimension < 1 || l.dimension > 3) fail(h5_path, "layer dimension out of range");
  l.layers = static_cast<int>(r.integer(layer.get(), "layers"));
  l.thickness = r.number(layer.get(), "thickness");
  const int dim = l.dimension;
  l.nodes = r.matrix_d(layer.get(), "nodes", dim);
  l.cells = r.matrix_i(layer.get(), "cells", l.nodes_per_cell());
  l.cell_layer = r.matrix_i(layer.get(), "cell_layer", 1).col(0);
  l.cell_part = r.matrix_i(layer.get(), "cell_part", 1).col(0);
  l.part_names = r.strings(layer.get(), "part_names");
  l.wall_facets = r.matrix_i(layer.get(), "wall_facets", dim);
  l.interface_facets = r.matrix_i(layer.get(), "interface_facets", dim);
  l.wall_facet_part = r.matrix_i(layer.get(), "wall_facet_part", 1).col(0);
  l.node_normals = r.matrix_d(layer.get(), "node_normals", dim);
  l.node_on_wall = r.matrix_i(layer.get(), "node_on_wall", 1).col(0);
  l.node_on_interface = r.matrix_i(layer.get(), "node_on_interface", 1).col(0);
  const auto n = l.nodes.rows();
  auto in_range = [n](const Eigen::MatrixXi& m) {
    return m.size() == 0 || (m.minCoeff() >= 0 && m.maxCoeff() < n);
  };
  if (!in_range(l.cells) || !in_range(l.wall_facets) || !in_range(l.interface_facets)) {
    fail(h5_path, "a cell or facet refers to a node that does not exist");
  }

  const Handle phi = r.group("/coupling/interface");
  p.interface_coupling = read_coupling(r, phi.get());
  const Handle gamma = r.group("/coupling/wall");
  p.wall_coupling = read_coupling(r, gamma.get());
  p.cell_flags = r.vector<std::uint8_t>(root, "cell_flags");

  const Handle report = r.group("/report");
  p.report.cells = static_cast<std::size_t>(r.integer(report.get(), "cells"));
  p.report.nodes = static_cast<std::size_t>(r.integer(report.get(), "nodes"));
  p.report.columns_shrunk = static_cast<std::size_t>(r.integer(report.get(), "columns_shrunk"));
  p.report.crease_normals = static_cast<std::size_t>(r.integer(report.get(), "crease_normals"));
  p.report.max_shrink = r.number(report.get(), "max_shrink");
  p.report.min_jacobian = r.number(report.get(), "min_jacobian");
  p.report.volume = r.number(report.get(), "volume");
  p.report.wall_measure = r.number(report.get(), "wall_measure");
  p.report.interface_measure = r.number(report.get(), "interface_measure");
  return p;
}

}  // namespace mpm
