// Validation, repair and isotropic remeshing of triangle surfaces with CGAL's
// Polygon_mesh_processing (PMP). CGAL lives in this translation unit only: it is header-heavy,
// and the rest of the project sees the plain arrays of triangle_mesh.hpp.
//
// validate_and_repair() works in two stages:
//  1. on the triangle soup (indices into V): merge coincident vertices (exactly, and border
//     vertices within the stitch tolerance), drop faces that repeat a corner and duplicate faces,
//     orient with PMP::orient_polygon_soup, whose visitor reports non-manifold edges/vertices;
//  2. on a CGAL::Surface_mesh: remove collinear faces, count components and borders, look for
//     self-intersections, orient closed surfaces outward.
// Each face carries its part and the index of the input face it came from as face properties,
// so parts follow their faces and messages can name faces the way the caller numbers them.

#include "mpmgeom/mesh_repair.hpp"
#include "format.hpp"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Polygon_mesh_processing/connected_components.h>
#include <CGAL/Polygon_mesh_processing/detect_features.h>
#include <CGAL/Polygon_mesh_processing/orient_polygon_soup.h>
#include <CGAL/Polygon_mesh_processing/orientation.h>
#include <CGAL/Polygon_mesh_processing/polygon_soup_to_polygon_mesh.h>
#include <CGAL/Polygon_mesh_processing/remesh.h>
#include <CGAL/Polygon_mesh_processing/repair_degeneracies.h>
#include <CGAL/Polygon_mesh_processing/self_intersections.h>
#include <CGAL/Polygon_mesh_processing/shape_predicates.h>
#include <CGAL/Surface_mesh.h>
#include <CGAL/boost/graph/Face_filtered_graph.h>
#include <CGAL/boost/graph/helpers.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <map>
#include <numbers>
#include <numeric>
#include <sstream>
#include <stdexcept>
#include <tuple>
#include <unordered_map>
#include <utility>

namespace mpmgeom {

namespace {

namespace PMP = CGAL::Polygon_mesh_processing;
using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Point = Kernel::Point_3;
using Mesh = CGAL::Surface_mesh<Point>;
using Face = Mesh::Face_index;
using Vertex = Mesh::Vertex_index;
using Halfedge = Mesh::Halfedge_index;
using Edge = Mesh::Edge_index;
using Triangle = std::array<std::size_t, 3>;
using EdgeKey = std::pair<std::size_t, std::size_t>;  // vertex indices, first < second

constexpr std::size_t kNone = std::numeric_limits<std::size_t>::max();

// ---------------------------------------------------------------------------------------------
// Messages

[[noreturn]] void fail(const std::string& name, const std::string& defect) {
  throw MeshError("mesh '" + name + "': " + defect);
}

using detail::format_number;
using detail::format_point;

std::string format_point(const Point& p) {
  return format_point(Eigen::Vector3d(p.x(), p.y(), p.z()));
}

// "1 face", "3 faces"
std::string count_of(std::size_t n, const std::string& singular, const std::string& plural) {
  return std::to_string(n) + ' ' + (n == 1 ? singular : plural);
}

// ---------------------------------------------------------------------------------------------
// Stage 1: the triangle soup

// Faces still in play, as parallel arrays: corners (indices into the input V), the input face
// each one is, and its part.
struct Soup {
  std::vector<Triangle> triangles;
  std::vector<std::size_t> origin;
  std::vector<int> part;

  std::size_t size() const { return triangles.size(); }
  void keep_if(const std::vector<char>& keep) {
    std::size_t out = 0;
    for (std::size_t f = 0; f < triangles.size(); ++f) {
      if (!keep[f]) continue;
      triangles[out] = triangles[f];
      origin[out] = origin[f];
      part[out] = part[f];
      ++out;
    }
    triangles.resize(out);
    origin.resize(out);
    part.resize(out);
  }
};

Triangle mapped(const Triangle& t, const std::vector<std::size_t>& rep) {
  return {rep[t[0]], rep[t[1]], rep[t[2]]};
}

bool repeats_a_corner(const Triangle& t) { return t[0] == t[1] || t[1] == t[2] || t[0] == t[2]; }

// Every face-edge as a sorted vertex pair, sorted: runs of equal keys are one edge and the run
// length is the number of faces on it (1: border, 2: manifold, more: non-manifold).
std::vector<EdgeKey> edge_uses(const std::vector<Triangle>& triangles,
                               const std::vector<std::size_t>& rep) {
  std::vector<EdgeKey> uses;
  uses.reserve(3 * triangles.size());
  for (const Triangle& t : triangles) {
    for (int k = 0; k < 3; ++k) {
      const std::size_t a = rep[t[k]];
      const std::size_t b = rep[t[(k + 1) % 3]];
      uses.emplace_back(std::min(a, b), std::max(a, b));
    }
  }
  std::sort(uses.begin(), uses.end());
  return uses;
}

// Calls visit(edge, number of faces on it) once per distinct edge.
template <typename Visit>
void for_each_edge(const std::vector<EdgeKey>& uses, Visit visit) {
  for (std::size_t i = 0; i < uses.size();) {
    std::size_t j = i + 1;
    while (j < uses.size() && uses[j] == uses[i]) ++j;
    visit(uses[i], j - i);
    i = j;
  }
}

std::size_t count_border_edges(const std::vector<Triangle>& triangles,
                               const std::vector<std::size_t>& rep) {
  std::size_t border = 0;
  for_each_edge(edge_uses(triangles, rep),
                [&](const EdgeKey&, std::size_t n) { border += n == 1; });
  return border;
}

std::vector<std::size_t> identity(std::size_t n) {
  std::vector<std::size_t> id(n);
  std::iota(id.begin(), id.end(), std::size_t{0});
  return id;
}

// rep[v] = the lowest-numbered vertex at exactly the same position as v.
std::vector<std::size_t> merge_coincident(const Eigen::MatrixX3d& V) {
  std::vector<std::size_t> rep(static_cast<std::size_t>(V.rows()));
  std::map<std::array<double, 3>, std::size_t> first;
  for (Eigen::Index v = 0; v < V.rows(); ++v) {
    const std::array<double, 3> key{V(v, 0), V(v, 1), V(v, 2)};
    rep[static_cast<std::size_t>(v)] =
        first.try_emplace(key, static_cast<std::size_t>(v)).first->second;
  }
  return rep;
}

struct UnionFind {
  std::vector<std::size_t> parent;
  explicit UnionFind(std::size_t n) : parent(identity(n)) {}
  std::size_t find(std::size_t v) {
    while (parent[v] != v) v = parent[v] = parent[parent[v]];
    return v;
  }
  void join(std::size_t a, std::size_t b) {  // the lower index stays the representative
    a = find(a);
    b = find(b);
    if (a != b) parent[std::max(a, b)] = std::min(a, b);
  }
};

// Merges border vertices (after `rep`) at most `tolerance` apart, unless an edge joins them
// (that would collapse a face): seams whose two sides were exported with slightly different
// round-off. Interior vertices are never moved. Returns the composed representative map.
std::vector<std::size_t> snap_border_vertices(const Eigen::MatrixX3d& V,
                                              const std::vector<Triangle>& triangles,
                                              const std::vector<std::size_t>& rep,
                                              double tolerance) {
  std::vector<std::vector<std::size_t>> neighbours(rep.size());
  std::vector<std::size_t> border;
  for_each_edge(edge_uses(triangles, rep), [&](const EdgeKey& e, std::size_t n) {
    if (n != 1) return;
    for (std::size_t v : {e.first, e.second}) {
      if (neighbours[v].empty()) border.push_back(v);
    }
    neighbours[e.first].push_back(e.second);
    neighbours[e.second].push_back(e.first);
  });
  if (border.size() < 2 || !(tolerance > 0.0)) return rep;

  // Border vertices binned in cubes of side `tolerance`; partners lie in the 27 around.
  using Cell = std::array<std::int64_t, 3>;
  auto cell_of = [&](std::size_t v) {
    return Cell{
        static_cast<std::int64_t>(std::floor(V(static_cast<Eigen::Index>(v), 0) / tolerance)),
        static_cast<std::int64_t>(std::floor(V(static_cast<Eigen::Index>(v), 1) / tolerance)),
        static_cast<std::int64_t>(std::floor(V(static_cast<Eigen::Index>(v), 2) / tolerance))};
  };
  std::map<Cell, std::vector<std::size_t>> bins;
  for (std::size_t v : border) bins[cell_of(v)].push_back(v);

  UnionFind sets(rep.size());
  for (std::size_t v : border) {
    const Cell c = cell_of(v);
    const Eigen::Vector3d p = V.row(static_cast<Eigen::Index>(v));
    for (std::int64_t dx = -1; dx <= 1; ++dx) {
      for (std::int64_t dy = -1; dy <= 1; ++dy) {
        for (std::int64_t dz = -1; dz <= 1; ++dz) {
          const auto bin = bins.find(Cell{c[0] + dx, c[1] + dy, c[2] + dz});
          if (bin == bins.end()) continue;
          for (std::size_t w : bin->second) {
            if (w <= v) continue;
            if ((V.row(static_cast<Eigen::Index>(w)).transpose() - p).norm() > tolerance) continue;
            const auto& nv = neighbours[v];
            if (std::find(nv.begin(), nv.end(), w) != nv.end()) continue;
            sets.join(v, w);
          }
        }
      }
    }
  }
  std::vector<std::size_t> snapped(rep.size());
  for (std::size_t v = 0; v < rep.size(); ++v) snapped[v] = sets.find(rep[v]);
  return snapped;
}

// Drops faces that repeat a corner under `rep` (zero area) and faces with the same corners as
// an earlier one, in either orientation (the earlier one, and its part, is kept).
void drop_degenerate_and_duplicates(Soup& soup, const std::vector<std::size_t>& rep,
                                    std::size_t& degenerate, std::size_t& duplicates) {
  std::vector<char> keep(soup.size(), 1);
  std::vector<std::pair<Triangle, std::size_t>> sorted;
  sorted.reserve(soup.size());
  for (std::size_t f = 0; f < soup.size(); ++f) {
    Triangle t = mapped(soup.triangles[f], rep);
    if (repeats_a_corner(t)) {
      keep[f] = 0;
      ++degenerate;
      continue;
    }
    std::sort(t.begin(), t.end());
    sorted.emplace_back(t, f);
  }
  std::sort(sorted.begin(), sorted.end());
  for (std::size_t i = 1; i < sorted.size(); ++i) {
    if (sorted[i].first == sorted[i - 1].first) {
      keep[sorted[i].second] = 0;
      ++duplicates;
    }
  }
  soup.keep_if(keep);
}

// Vertices whose faces form more than one fan (faces joined through the edges at the vertex),
// e.g. two cones touching at their tips. Assumes no edge has more than two faces.
std::vector<std::size_t> pinched_vertices(const std::vector<Triangle>& triangles,
                                          std::size_t vertex_count) {
  std::vector<std::vector<std::size_t>> faces_at(vertex_count);
  for (std::size_t f = 0; f < triangles.size(); ++f) {
    for (std::size_t v : triangles[f]) faces_at[v].push_back(f);
  }
  std::vector<std::size_t> pinched;
  for (std::size_t v = 0; v < vertex_count; ++v) {
    const auto& around = faces_at[v];
    // Fans by union-find over the local face list; faces sharing another corner u share the
    // edge v-u.
    UnionFind fans_of(around.size());
    std::map<std::size_t, std::size_t> first_face_with;  // other corner -> local face index
    for (std::size_t i = 0; i < around.size(); ++i) {
      for (std::size_t u : triangles[around[i]]) {
        if (u == v) continue;
        const auto [it, inserted] = first_face_with.try_emplace(u, i);
        if (!inserted) fans_of.join(i, it->second);
      }
    }
    std::size_t fans = 0;
    for (std::size_t i = 0; i < around.size(); ++i) fans += fans_of.find(i) == i;
    if (fans > 1) pinched.push_back(v);
  }
  return pinched;
}

// What PMP::orient_polygon_soup had to cut to orient the soup.
struct Singularities {
  std::map<EdgeKey, std::size_t> edges;  // non-manifold edge -> number of faces on it
  std::vector<std::size_t> vertices;     // non-manifold vertices
};

// The soup orienter copies its visitor, so this one only points at the record.
struct OrientationVisitor : PMP::Default_orientation_visitor {
  Singularities* found = nullptr;
  // Called once per face on the edge.
  void non_manifold_edge(std::size_t a, std::size_t b, std::size_t faces) {
    found->edges.try_emplace({std::min(a, b), std::max(a, b)}, faces);
  }
  void non_manifold_vertex(std::size_t v, std::size_t /*fans*/) { found->vertices.push_back(v); }
};

// ---------------------------------------------------------------------------------------------
// Stage 2: the Surface_mesh

struct Labels {
  Mesh::Property_map<Face, int> part;
  Mesh::Property_map<Face, std::size_t> origin;  // input face index
};

Labels add_labels(Mesh& mesh) {
  return {mesh.add_property_map<Face, int>("f:part", -1).first,
          mesh.add_property_map<Face, std::size_t>("f:origin", kNone).first};
}

Eigen::Vector3d to_eigen(const Point& p) { return {p.x(), p.y(), p.z()}; }

Eigen::Vector3d face_normal(const Mesh& mesh, Face f) {  // not normalised: twice the area
  const Halfedge h = mesh.halfedge(f);
  const Eigen::Vector3d a = to_eigen(mesh.point(mesh.source(h)));
  const Eigen::Vector3d b = to_eigen(mesh.point(mesh.target(h)));
  const Eigen::Vector3d c = to_eigen(mesh.point(mesh.target(mesh.next(h))));
  return (b - a).cross(c - a);
}

Eigen::Vector3d centroid(const Mesh& mesh, Face f) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (Vertex v : CGAL::vertices_around_face(mesh.halfedge(f), mesh))
    sum += to_eigen(mesh.point(v));
  return sum / 3.0;
}

// A collinear face is removed by flipping its longest edge (or collapsing a short one); the
// face that then covers the area is the neighbour across the longest edge, so the degenerate
// face takes that neighbour's part and origin beforehand.
void label_like_longest_edge_neighbour(Mesh& mesh, const Labels& labels, Face f) {
  Halfedge longest = mesh.halfedge(f);
  double longest_length = -1.0;
  for (Halfedge h : CGAL::halfedges_around_face(mesh.halfedge(f), mesh)) {
    const double length =
        CGAL::squared_distance(mesh.point(mesh.source(h)), mesh.point(mesh.target(h)));
    if (length > longest_length) {
      longest_length = length;
      longest = h;
    }
  }
  const Face neighbour = mesh.face(mesh.opposite(longest));
  if (neighbour == Mesh::null_face()) return;
  labels.part[f] = labels.part[neighbour];
  labels.origin[f] = labels.origin[neighbour];
}

// Faces that an Euler operation created get the label of an adjacent labelled face.
void label_new_faces(Mesh& mesh, const Labels& labels) {
  bool changed = true;
  while (changed) {
    changed = false;
    for (Face f : mesh.faces()) {
      if (labels.part[f] >= 0) continue;
      for (Halfedge h : CGAL::halfedges_around_face(mesh.halfedge(f), mesh)) {
        const Face g = mesh.face(mesh.opposite(h));
        if (g != Mesh::null_face() && labels.part[g] >= 0) {
          labels.part[f] = labels.part[g];
          labels.origin[f] = labels.origin[g];
          changed = true;
          break;
        }
      }
    }
  }
}

std::size_t count_border_halfedges(const Mesh& mesh) {
  std::size_t border = 0;
  for (Halfedge h : mesh.halfedges()) border += mesh.is_border(h);
  return border;
}

// The mesh as arrays: vertices in the order of `vertex_order` (ascending), faces by origin.
TriangleMesh to_triangle_mesh(Mesh& mesh, const Labels& labels,
                              const Mesh::Property_map<Vertex, std::size_t>& vertex_order,
                              const std::vector<std::string>& part_names) {
  std::vector<Vertex> vertices(mesh.vertices().begin(), mesh.vertices().end());
  std::stable_sort(vertices.begin(), vertices.end(),
                   [&](Vertex a, Vertex b) { return vertex_order[a] < vertex_order[b]; });
  std::vector<Face> faces(mesh.faces().begin(), mesh.faces().end());
  std::stable_sort(faces.begin(), faces.end(),
                   [&](Face a, Face b) { return labels.origin[a] < labels.origin[b]; });

  auto index = mesh.add_property_map<Vertex, int>("v:output_index", -1).first;
  TriangleMesh out;
  out.V.resize(static_cast<Eigen::Index>(vertices.size()), 3);
  for (std::size_t i = 0; i < vertices.size(); ++i) {
    index[vertices[i]] = static_cast<int>(i);
    out.V.row(static_cast<Eigen::Index>(i)) = to_eigen(mesh.point(vertices[i])).transpose();
  }
  out.F.resize(static_cast<Eigen::Index>(faces.size()), 3);
  out.part.resize(static_cast<Eigen::Index>(faces.size()));
  for (std::size_t i = 0; i < faces.size(); ++i) {
    const auto row = static_cast<Eigen::Index>(i);
    int k = 0;
    for (Vertex v : CGAL::vertices_around_face(mesh.halfedge(faces[i]), mesh))
      out.F(row, k++) = index[v];
    out.part(row) = std::max(labels.part[faces[i]], 0);
  }
  mesh.remove_property_map(index);
  out.part_names = part_names;
  return out;
}

// Input checks shared by both entry points: index ranges, part vector, finite positions.
// Returns the part of each face (all 0 if `part` is empty) and the part names to output.
std::pair<std::vector<int>, std::vector<std::string>> checked_parts(const TriangleMesh& mesh,
                                                                    const std::string& name) {
  const Eigen::Index nv = mesh.V.rows();
  const Eigen::Index nf = mesh.F.rows();
  if (nf == 0) fail(name, "contains no triangles");
  if (mesh.V.cols() != 3 || mesh.F.cols() != 3) fail(name, "V and F must have 3 columns");
  for (Eigen::Index v = 0; v < nv; ++v) {
    if (!mesh.V.row(v).allFinite()) {
      fail(name, "non-finite coordinate at vertex " + std::to_string(v) + " " +
                     format_point(Eigen::Vector3d(mesh.V.row(v).transpose())));
    }
  }
  for (Eigen::Index f = 0; f < nf; ++f) {
    for (int k = 0; k < 3; ++k) {
      if (mesh.F(f, k) < 0 || mesh.F(f, k) >= nv) {
        fail(name, "face " + std::to_string(f) + " references vertex " +
                       std::to_string(mesh.F(f, k)) + " of " + std::to_string(nv));
      }
    }
  }
  std::vector<std::string> names = mesh.part_names;
  std::vector<int> part(static_cast<std::size_t>(nf), 0);
  if (mesh.part.size() == 0) {
    if (names.empty()) names.emplace_back("mesh");
    return {part, names};
  }
  if (mesh.part.size() != nf) {
    fail(name, "part has " + std::to_string(mesh.part.size()) + " entries for " +
                   std::to_string(nf) + " faces");
  }
  for (Eigen::Index f = 0; f < nf; ++f) {
    if (mesh.part(f) < 0 || static_cast<std::size_t>(mesh.part(f)) >= names.size()) {
      fail(name, "face " + std::to_string(f) + " has part " + std::to_string(mesh.part(f)) +
                     " of " + std::to_string(names.size()));
    }
    part[static_cast<std::size_t>(f)] = mesh.part(f);
  }
  return {part, names};
}

}  // namespace

TriangleMesh validate_and_repair(const TriangleMesh& mesh, const std::string& name,
                                 const RepairOptions& options, RepairReport* report) {
  RepairReport local;
  RepairReport& rep = report ? *report : local;
  rep = RepairReport{};
  if (!std::isfinite(options.stitch_tolerance) || options.stitch_tolerance < 0.0) {
    fail(name, "stitch_tolerance must be finite and non-negative (0 = automatic)");
  }
  auto [input_part, part_names] = checked_parts(mesh, name);
  const std::size_t input_faces = static_cast<std::size_t>(mesh.F.rows());
  const std::size_t input_vertices = static_cast<std::size_t>(mesh.V.rows());

  // --- Stage 1: soup ---------------------------------------------------------------------
  Soup soup;
  soup.triangles.resize(input_faces);
  for (std::size_t f = 0; f < input_faces; ++f) {
    const auto row = static_cast<Eigen::Index>(f);
    soup.triangles[f] = {static_cast<std::size_t>(mesh.F(row, 0)),
                         static_cast<std::size_t>(mesh.F(row, 1)),
                         static_cast<std::size_t>(mesh.F(row, 2))};
  }
  soup.origin = identity(input_faces);
  soup.part = input_part;

  std::size_t degenerate = 0;
  std::size_t duplicates = 0;
  std::vector<std::size_t> vertex_rep = merge_coincident(mesh.V);
  drop_degenerate_and_duplicates(soup, vertex_rep, degenerate, duplicates);

  double tolerance = options.stitch_tolerance;
  if (tolerance == 0.0) {
    tolerance = 1e-6 * (mesh.V.colwise().maxCoeff() - mesh.V.colwise().minCoeff()).norm();
  }
  if (!soup.triangles.empty()) {
    vertex_rep = snap_border_vertices(mesh.V, soup.triangles, vertex_rep, tolerance);
    drop_degenerate_and_duplicates(soup, vertex_rep, degenerate, duplicates);
  }
  // The collinear faces found on the mesh below are added to `degenerate`; an empty soup here
  // means every face repeated a corner.
  if (soup.triangles.empty()) {
    fail(name,
         "no triangles left after removing " +
             count_of(degenerate, "degenerate face", "degenerate faces") +
             (duplicates > 0 ? " and " + count_of(duplicates, "duplicate", "duplicates") : ""));
  }
  const std::size_t border_before = count_border_edges(soup.triangles, identity(input_vertices));
  const std::size_t border_after = count_border_edges(soup.triangles, vertex_rep);
  rep.edges_stitched = border_before > border_after ? (border_before - border_after) / 2 : 0;

  // Compact to the vertices in use, keeping the input order (each group is represented by its
  // lowest input index).
  std::vector<std::size_t> compact(input_vertices, kNone);
  for (const Triangle& t : soup.triangles) {
    for (std::size_t v : t) compact[vertex_rep[v]] = 0;
  }
  std::vector<Point> points;
  std::vector<std::size_t> point_origin;
  for (std::size_t v = 0; v < input_vertices; ++v) {
    if (compact[v] == kNone) continue;
    compact[v] = points.size();
    const auto row = static_cast<Eigen::Index>(v);
    points.emplace_back(mesh.V(row, 0), mesh.V(row, 1), mesh.V(row, 2));
    point_origin.push_back(v);
  }
  std::vector<Triangle> polygons(soup.size());
  for (std::size_t f = 0; f < soup.size(); ++f) {
    for (int k = 0; k < 3; ++k) polygons[f][k] = compact[vertex_rep[soup.triangles[f][k]]];
  }

  const std::vector<Triangle> unoriented = polygons;
  Singularities singular;
  OrientationVisitor visitor;
  visitor.found = &singular;
  const std::size_t points_before = points.size();
  const bool oriented =
      PMP::orient_polygon_soup(points, polygons, PMP::parameters::visitor(visitor));
  if (!singular.edges.empty()) {
    const auto& [e, faces] = *singular.edges.begin();  // the lowest-numbered vertex pair
    const Eigen::Vector3d mid = 0.5 * (to_eigen(points[e.first]) + to_eigen(points[e.second]));
    fail(name, count_of(singular.edges.size(), "non-manifold edge", "non-manifold edges") +
                   " (first at " + format_point(mid) + ", shared by " + std::to_string(faces) +
                   " faces)");
  }
  if (!singular.vertices.empty()) {
    // The orienter also reports the vertices at the ends of the cut it makes through a
    // non-orientable surface; only pinches of the input itself are non-manifold vertices.
    const std::vector<std::size_t> pinched = pinched_vertices(unoriented, points_before);
    if (!pinched.empty()) {
      fail(name, count_of(pinched.size(), "non-manifold vertex", "non-manifold vertices") +
                     " (first at " + format_point(points[pinched.front()]) +
                     ": the faces around it form separate fans)");
    }
  }
  if (!oriented || points.size() != points_before ||
      !PMP::is_polygon_soup_a_polygon_mesh(polygons)) {
    fail(name,
         "cannot be oriented consistently (a non-orientable surface, such as a Moebius strip)");
  }

  // --- Stage 2: mesh ---------------------------------------------------------------------
  Mesh sm;
  PMP::polygon_soup_to_polygon_mesh(points, polygons, sm);
  // The converter adds every point as a vertex and every polygon as a face, in order.
  const Labels labels = add_labels(sm);
  auto vertex_origin = sm.add_property_map<Vertex, std::size_t>("v:origin", kNone).first;
  for (std::size_t v = 0; v < points.size(); ++v) {
    vertex_origin[Vertex(static_cast<Mesh::size_type>(v))] = point_origin[v];
  }
  for (std::size_t f = 0; f < soup.size(); ++f) {
    const Face face(static_cast<Mesh::size_type>(f));
    labels.part[face] = soup.part[f];
    labels.origin[face] = soup.origin[f];
  }

  std::vector<Face> collinear;
  PMP::degenerate_faces(sm, std::back_inserter(collinear));
  if (!collinear.empty()) {
    for (Face f : collinear) label_like_longest_edge_neighbour(sm, labels, f);
    PMP::remove_degenerate_faces(sm);
    sm.collect_garbage();
    label_new_faces(sm, labels);
    degenerate += collinear.size();
    std::vector<Face> left;
    PMP::degenerate_faces(sm, std::back_inserter(left));
    if (!left.empty()) {
      fail(name, count_of(left.size(), "degenerate face", "degenerate faces") +
                     " (zero area) could not be removed (first at " +
                     format_point(centroid(sm, left.front())) + ")");
    }
    if (sm.number_of_faces() == 0) {
      fail(name,
           "no triangles left after removing " +
               count_of(degenerate, "degenerate face", "degenerate faces") +
               (duplicates > 0 ? " and " + count_of(duplicates, "duplicate", "duplicates") : ""));
    }
  }
  rep.degenerate_faces_removed = degenerate;
  rep.duplicate_faces_removed = duplicates;

  auto component = sm.add_property_map<Face, std::size_t>("f:component", 0).first;
  rep.components = PMP::connected_components(sm, component);
  rep.border_edges = count_border_halfedges(sm);
  rep.closed = CGAL::is_closed(sm);
  if (options.require_closed && !rep.closed) {
    fail(name, "open surface (" + count_of(rep.border_edges, "border edge", "border edges") +
                   ") where a closed surface is required");
  }

  std::vector<std::pair<Face, Face>> intersecting;
  PMP::self_intersections(sm.faces(), sm, std::back_inserter(intersecting));
  rep.self_intersecting_pairs = intersecting.size();
  if (options.reject_self_intersections && !intersecting.empty()) {
    std::size_t a = labels.origin[intersecting.front().first];
    std::size_t b = labels.origin[intersecting.front().second];
    if (a > b) std::swap(a, b);
    fail(name, count_of(intersecting.size(), "pair", "pairs") +
                   " of self-intersecting faces (first: faces " + std::to_string(a) + " and " +
                   std::to_string(b) + ")");
  }

  // Orientation. orient_polygon_soup made each component consistent, keeping an arbitrary
  // face's orientation. Closed components then face outward (PMP::orient_to_bound_a_volume also
  // turns cavities inside out, so that the faces bound the volume); open ones keep the
  // orientation most of their input faces had.
  std::vector<char> component_closed(rep.components, 1);
  for (Halfedge h : sm.halfedges()) {
    if (sm.is_border(h)) component_closed[component[sm.face(sm.opposite(h))]] = 0;
  }
  auto input_normal = [&](Face f) -> Eigen::Vector3d {
    if (labels.origin[f] == kNone) return Eigen::Vector3d::Zero();
    const auto row = static_cast<Eigen::Index>(labels.origin[f]);
    const Eigen::Vector3d a = mesh.V.row(mesh.F(row, 0));
    const Eigen::Vector3d b = mesh.V.row(mesh.F(row, 1));
    const Eigen::Vector3d c = mesh.V.row(mesh.F(row, 2));
    return (b - a).cross(c - a);
  };
  auto reversed_count = [&](std::vector<std::size_t>& per_component) {
    per_component.assign(rep.components, 0);
    for (Face f : sm.faces()) {
      per_component[component[f]] += face_normal(sm, f).dot(input_normal(f)) < 0.0;
    }
  };
  std::vector<std::size_t> faces_in(rep.components, 0);
  for (Face f : sm.faces()) ++faces_in[component[f]];
  std::vector<std::size_t> reversed;
  reversed_count(reversed);
  auto faces_of = [&](std::size_t c) {
    std::vector<Face> faces;
    for (Face f : sm.faces()) {
      if (component[f] == c) faces.push_back(f);
    }
    return faces;
  };
  for (std::size_t c = 0; c < rep.components; ++c) {
    if (!component_closed[c] && 2 * reversed[c] > faces_in[c]) {
      PMP::reverse_face_orientations(faces_of(c), sm);
    }
  }
  if (rep.closed && intersecting.empty()) {
    PMP::orient_to_bound_a_volume(sm);
  } else {
    for (std::size_t c = 0; c < rep.components; ++c) {
      if (!component_closed[c]) continue;
      const CGAL::Face_filtered_graph<Mesh> piece(sm, c, component);
      if (!PMP::is_outward_oriented(piece)) PMP::reverse_face_orientations(faces_of(c), sm);
    }
  }
  reversed_count(reversed);
  std::size_t inward_components = 0;
  for (std::size_t c = 0; c < rep.components; ++c) {
    if (component_closed[c] && 2 * reversed[c] > faces_in[c]) {
      // Most of it faced inward: it was reversed as a whole; the faces now unchanged were the
      // ones that disagreed with their neighbours.
      ++inward_components;
      rep.inward_faces_reversed += faces_in[c];
      rep.faces_reoriented += faces_in[c] - reversed[c];
    } else {
      rep.faces_reoriented += reversed[c];
    }
  }
  rep.outward = !rep.closed || PMP::is_outward_oriented(sm);

  if (rep.degenerate_faces_removed > 0) {
    rep.repairs.push_back(
        "removed " + count_of(rep.degenerate_faces_removed, "degenerate face", "degenerate faces") +
        " (zero area)");
  }
  if (rep.duplicate_faces_removed > 0) {
    rep.repairs.push_back(
        "removed " + count_of(rep.duplicate_faces_removed, "duplicate face", "duplicate faces"));
  }
  if (rep.edges_stitched > 0) {
    rep.repairs.push_back("stitched " + count_of(rep.edges_stitched, "pair", "pairs") +
                          " of coincident border edges (tolerance " + format_number(tolerance) +
                          ")");
  }
  if (rep.faces_reoriented > 0) {
    rep.repairs.push_back("flipped " + count_of(rep.faces_reoriented, "face", "faces") +
                          " to agree with their neighbours");
  }
  if (inward_components > 0) {
    rep.repairs.push_back("reversed " +
                          count_of(inward_components, "closed surface", "closed surfaces") + " (" +
                          count_of(rep.inward_faces_reversed, "face", "faces") +
                          ") that faced inward, so that normals point out of the volume");
  }

  sm.remove_property_map(component);
  return to_triangle_mesh(sm, labels, vertex_origin, part_names);
}

TriangleMesh remesh_isotropic(const TriangleMesh& mesh, double target_edge_length, int iterations,
                              double feature_angle_deg) {
  if (!std::isfinite(target_edge_length) || !(target_edge_length > 0.0)) {
    throw std::invalid_argument("remesh_isotropic: target_edge_length must be finite and positive");
  }
  if (iterations < 1)
    throw std::invalid_argument("remesh_isotropic: iterations must be at least 1");
  if (!(feature_angle_deg > 0.0 && feature_angle_deg < 180.0)) {
    throw std::invalid_argument("remesh_isotropic: feature_angle_deg must lie in (0, 180)");
  }
  const std::string name = "remesh_isotropic input";
  auto [input_part, part_names] = checked_parts(mesh, name);

  std::vector<Point> points;
  points.reserve(static_cast<std::size_t>(mesh.V.rows()));
  for (Eigen::Index v = 0; v < mesh.V.rows(); ++v)
    points.emplace_back(mesh.V(v, 0), mesh.V(v, 1), mesh.V(v, 2));
  std::vector<Triangle> polygons(static_cast<std::size_t>(mesh.F.rows()));
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    for (int k = 0; k < 3; ++k)
      polygons[static_cast<std::size_t>(f)][k] = static_cast<std::size_t>(mesh.F(f, k));
  }
  if (!PMP::is_polygon_soup_a_polygon_mesh(polygons)) {
    fail(name, "not a consistently oriented manifold surface; run validate_and_repair() first");
  }

  Mesh sm;
  PMP::polygon_soup_to_polygon_mesh(points, polygons, sm);
  const Labels labels = add_labels(sm);
  for (std::size_t f = 0; f < polygons.size(); ++f) {
    const Face face(static_cast<Mesh::size_type>(f));
    labels.part[face] = input_part[f];
    labels.origin[face] = f;
  }
  // Isolated input vertices would stay isolated; drop them.
  for (Vertex v : sm.vertices()) {
    if (sm.is_isolated(v)) sm.remove_vertex(v);
  }
  sm.collect_garbage();

  // Constrained edges are split and collapsed along themselves but never flipped, and their
  // vertices only move along them: borders, part boundaries and sharp edges keep their place.
  auto constrained = sm.add_property_map<Edge, bool>("e:constrained", false).first;
  PMP::detect_sharp_edges(sm, feature_angle_deg, constrained);
  for (Edge e : sm.edges()) {
    const Halfedge h = sm.halfedge(e);
    const Face f = sm.face(h);
    const Face g = sm.face(sm.opposite(h));
    if (f == Mesh::null_face() || g == Mesh::null_face() || labels.part[f] != labels.part[g]) {
      constrained[e] = true;
    }
  }

  // Constrained edges may be collapsed along their polyline, which would cut the corners of a
  // border or boundary: vertices where constrained edges meet other than two at a time, or where
  // the polyline turns by more than the feature angle, stay fixed.
  auto corner = sm.add_property_map<Vertex, bool>("v:corner", false).first;
  const double cos_turn = std::cos(feature_angle_deg * std::numbers::pi / 180.0);
  for (Vertex v : sm.vertices()) {
    std::vector<Eigen::Vector3d> along;  // unit vectors from v along its constrained edges
    for (Halfedge h : CGAL::halfedges_around_target(sm.halfedge(v), sm)) {
      if (!constrained[sm.edge(h)]) continue;
      along.push_back((to_eigen(sm.point(sm.source(h))) - to_eigen(sm.point(v))).normalized());
    }
    if (along.empty()) continue;
    // Straight on: the two directions are opposite, -along[0].dot(along[1]) = cos(0) = 1.
    corner[v] = along.size() != 2 || -along[0].dot(along[1]) < cos_turn;
  }

  // The part is the patch id: new faces inherit the part of the face they were cut from, and
  // edges between patches stay patch borders.
  PMP::isotropic_remeshing(sm.faces(), target_edge_length, sm,
                           PMP::parameters::number_of_iterations(static_cast<unsigned>(iterations))
                               .edge_is_constrained_map(constrained)
                               .vertex_is_constrained_map(corner)
                               .face_patch_map(labels.part)
                               .protect_constraints(false));
  sm.collect_garbage();
  label_new_faces(sm, labels);

  // New vertices have no input order; keep CGAL's.
  auto order = sm.add_property_map<Vertex, std::size_t>("v:order", 0).first;
  for (Vertex v : sm.vertices()) order[v] = v.idx();
  // Faces in CGAL's order too: after remeshing there is no meaningful input face per face.
  for (Face f : sm.faces()) labels.origin[f] = f.idx();
  return to_triangle_mesh(sm, labels, order, part_names);
}

}  // namespace mpmgeom
