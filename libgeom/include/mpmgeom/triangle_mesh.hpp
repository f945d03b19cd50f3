// Surface-mesh import and export for wall and obstacle geometry.
//
// Everything here is plain data (Eigen arrays, std types): assimp stays a private dependency of
// mpm_geom, so the solver and its tests never see an assimp header.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <stdexcept>
#include <string>
#include <vector>

namespace mpmgeom {

/// A triangle surface with named parts (libigl-style arrays).
///
///   V           #V x 3  vertex positions
///   F           #F x 3  vertex indices into V, counter-clockwise seen from outside
///   part        #F      index into part_names of the part each face belongs to
///   part_names  #parts  part names, unique
///
/// load_mesh() returns only vertices referenced by F and no face with a repeated vertex index;
/// it does not check that the surface is closed, manifold or consistently oriented.
struct TriangleMesh {
  Eigen::MatrixX3d V;
  Eigen::MatrixX3i F;
  Eigen::VectorXi part;
  std::vector<std::string> part_names;
};

/// R = Rz * Ry * Rx for angles (x, y, z) in degrees: rotations about the fixed x, then y, then z
/// axes (ImportOptions' rotation, and the scene's other rotations, which follow it).
Eigen::Matrix3d rotation_from_degrees(const Eigen::Vector3d& degrees);

/// How load_mesh() places the file's geometry in the simulation frame. A point p of the file
/// (after its own node transforms) becomes  R * (scale * p) + translation,  with
/// R = Rz * Ry * Rx: rotations about the fixed x, then y, then z axes through the origin, in
/// degrees.
struct ImportOptions {
  double scale = 1.0;
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  Eigen::Vector3d rotation_deg = Eigen::Vector3d::Zero();
  /// Vertices at most this far apart (in output units, i.e. after scaling) are merged. 0 selects
  /// 1e-9 of the bounding-box diagonal: in effect exact-position welding, since positions
  /// arrive as float and one float step is ~6e-8 of the coordinate.
  double weld_tolerance = 0.0;
  /// Parse the file in a child process (the default): assimp is a large parser of untrusted
  /// input, and a malformed file can make it abort, loop or allocate without bound. The child
  /// is killed past a memory budget (memory_budget_bytes) or a time budget (20 s + 1 s per MB of
  /// CPU time, ten times that of wall clock), and any end of it other than a mesh is a
  /// MeshError. The fuzz target turns this off to see inside assimp.
  bool isolate = true;
  /// The child's resident memory budget. 0 selects 64 times the file size, at least 4 GiB, at
  /// most 3/4 of the machine; a given budget is also held to 3/4 of the machine.
  std::uint64_t memory_budget_bytes = 0;

  /// True if the options can be used: scale finite and > 0, translation and rotation finite,
  /// weld_tolerance finite and >= 0. Otherwise false, and *why (if given) says which one.
  bool valid(std::string* why = nullptr) const;
};

/// What load_mesh() changed or left out, for logs and tests.
struct ImportReport {
  std::size_t input_vertices = 0;            ///< vertices handed over by assimp, before welding
  std::size_t input_triangles = 0;           ///< triangles after triangulation, counting instances
  std::size_t skipped_primitives = 0;        ///< points and lines, which bound nothing
  std::size_t dropped_degenerate_faces = 0;  ///< faces with a repeated vertex after welding
  double weld_tolerance = 0.0;               ///< the absolute tolerance actually used
};

/// A defective mesh file, mesh or option. what() is one line: "mesh '<file>': <defect>".
class MeshError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

/// Loads any surface format assimp reads (STL ascii/binary, OBJ, PLY, OFF, glTF...).
///
/// Applies the node transforms of the file (flipping the winding under mirroring ones), then
/// `options`; triangulates polygons; skips point and line primitives; welds vertices closer
/// than the weld tolerance, across parts too; drops faces that then repeat a vertex. A part is
/// named after the assimp mesh, else its node, else "part<k>"; meshes with the same name share
/// a part. Positions pass through assimp as float, so expect single-precision round-off.
///
/// Throws MeshError if the file is missing or unreadable, assimp cannot parse it, a position is
/// not finite, the options are invalid, or no non-degenerate triangle remains; and, with
/// options.isolate, if the reader dies, or passes its memory or time budget.
///
/// @param[in]  file     mesh file; the format is detected by assimp
/// @param[in]  options  placement and welding
/// @param[out] report   optional; filled with what the import dropped and merged
TriangleMesh load_mesh(const std::filesystem::path& file, const ImportOptions& options = {},
                       ImportReport* report = nullptr);

/// How save_mesh() encodes formats that have both variants.
struct SaveOptions {
  bool binary = true;  ///< STL and PLY: binary (true) or ASCII; OBJ is always text
};

/// Writes a mesh (for tests and tools) through assimp's exporter, the format chosen by the
/// extension: .stl, .obj (without .mtl; one object per part) or .ply. STL and PLY have no
/// parts, so part names survive only in OBJ. Positions are rounded to float. `part` may be
/// empty: all faces then form one part, named part_names[0] or else "mesh".
/// Throws MeshError if the mesh is inconsistent (index out of range, non-finite position, sizes
/// that do not match), the extension is unsupported or writing fails.
void save_mesh(const TriangleMesh& mesh, const std::filesystem::path& file,
               const SaveOptions& options = {});

/// Sum of the triangle areas.
double surface_area(const TriangleMesh& mesh);

/// Axis-aligned box of the rows of V; empty (isEmpty()) if V has none.
Eigen::AlignedBox3d bounding_box(const TriangleMesh& mesh);

/// Throws MeshError when the mesh is implausibly large for the domain it is placed in: its
/// bounding-box diagonal more than `factor` times `domain_diagonal` (typically coordinates in
/// millimetres for a scene in metres; the message suggests the scale). Call it before
/// remeshing at the grid spacing or filling on its lattice, whose work grows with the square or
/// the cube of that ratio: a mesh 1000 times too large would never finish.
void check_extent(const TriangleMesh& mesh, const std::string& name, double domain_diagonal,
                  double factor = 20.0);

}  // namespace mpmgeom
