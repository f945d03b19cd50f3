// Validation, repair and isotropic remeshing of imported surfaces (CGAL inside, plain arrays out).
#pragma once

#include <cstddef>
#include <string>
#include <vector>

#include "mpmgeom/triangle_mesh.hpp"

namespace mpmgeom {

struct RepairOptions {
  /// The surface must bound a volume (a source volume, a closed structure): an open boundary
  /// that stitching cannot close is an error.
  bool require_closed = false;
  /// Self-intersections are an error (true) or only reported (false).
  bool reject_self_intersections = true;
  /// Border vertices at most this far apart are merged (stitching seams whose two sides were
  /// written with different round-off); interior vertices are never moved. 0 selects 1e-6 of
  /// the bounding-box diagonal. Vertices at exactly the same position are always merged.
  double stitch_tolerance = 0.0;
};

/// What validate_and_repair() found and changed.
struct RepairReport {
  /// Zero-area faces: two corners at the same position (dropped) or three collinear corners
  /// (removed by PMP::remove_degenerate_faces, which flips or collapses an edge; the face
  /// count may then stay the same).
  std::size_t degenerate_faces_removed = 0;
  std::size_t duplicate_faces_removed = 0;  ///< same three corners as an earlier face
  std::size_t faces_reoriented = 0;         ///< faces flipped to agree with their neighbours
  /// Faces of closed surfaces that (mostly) faced inward and were reversed as a whole.
  std::size_t inward_faces_reversed = 0;
  std::size_t edges_stitched = 0;  ///< border edge pairs merged
  std::size_t components = 0;      ///< connected components after repair
  std::size_t border_edges = 0;    ///< after repair; 0 for a closed surface
  bool closed = false;
  bool outward = true;  ///< closed surfaces: normals point out of the enclosed volume
  std::size_t self_intersecting_pairs = 0;  ///< pairs of faces that intersect (not neighbours)
  std::vector<std::string> repairs;         ///< one human-readable line per repair made
};

/// Checks a surface and repairs what can be repaired: merges coincident vertices (stitching
/// border edges), removes degenerate and duplicate faces, orients faces consistently. Closed
/// surfaces end up bounding their volume: normals point out of it (a cavity's surface points
/// into the cavity). Open components keep the orientation most of their faces had.
///
/// Rejects, with MeshError "mesh '<name>': <defect>" (one line), what cannot be repaired:
/// non-finite coordinates, indices or parts out of range, non-manifold edges or vertices left
/// after the repairs, a non-orientable surface, degenerate faces that cannot be removed, nothing
/// left, an open boundary when require_closed, self-intersections (unless allowed). Face
/// numbers in messages are rows of mesh.F.
///
/// The result lists vertices and faces in input order, without unreferenced vertices (a valid
/// mesh comes back unchanged); parts (mesh.part; all 0 if empty) follow their faces and
/// part_names are kept (["mesh"] if empty).
///
/// @param[in]  mesh     the surface, e.g. from load_mesh()
/// @param[in]  name     names the mesh in messages (usually the file)
/// @param[in]  options  what is an error; stitch tolerance (invalid: MeshError)
/// @param[out] report   optional; what was found and changed
TriangleMesh validate_and_repair(const TriangleMesh& mesh, const std::string& name,
                                 const RepairOptions& options = {}, RepairReport* report = nullptr);

/// CGAL isotropic remeshing to `target_edge_length` (about the grid spacing h), keeping
/// borders, part boundaries and sharp edges (angle between the face normals above
/// `feature_angle_deg`) in place: they are split and collapsed along themselves, never moved
/// off, and their corners (where they meet, or turn by more than `feature_angle_deg`) stay.
/// New vertices are projected onto the input surface. Parts follow their faces: the part is
/// CGAL's patch id, so new faces take the part of the face they were cut from.
///
/// Expects a manifold, consistently oriented mesh (the output of validate_and_repair());
/// throws MeshError otherwise, and std::invalid_argument for a target length that is not
/// positive and finite, iterations < 1 or a feature angle outside (0, 180).
TriangleMesh remesh_isotropic(const TriangleMesh& mesh, double target_edge_length,
                              int iterations = 3, double feature_angle_deg = 60.0);

}  // namespace mpmgeom
