// Surface-mesh import/export through assimp, into the plain arrays of triangle_mesh.hpp.

#include "format.hpp"
#include "mpmgeom/triangle_mesh.hpp"

#include <assimp/config.h>
#include <assimp/material.h>
#include <assimp/postprocess.h>
#include <assimp/scene.h>
#include <assimp/Exporter.hpp>
#include <assimp/Importer.hpp>

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <limits>
#include <memory>
#include <numbers>
#include <sstream>
#include <string_view>
#include <system_error>
#include <unordered_map>
#include <utility>

namespace mpmgeom {

Eigen::Matrix3d rotation_from_degrees(const Eigen::Vector3d& degrees) {
  constexpr double deg = std::numbers::pi / 180.0;
  return (Eigen::AngleAxisd(degrees.z() * deg, Eigen::Vector3d::UnitZ()) *
          Eigen::AngleAxisd(degrees.y() * deg, Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(degrees.x() * deg, Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

namespace {

namespace fs = std::filesystem;

// Messages must stay on one line (they end up in logs and in ctest output); assimp's own error
// strings sometimes carry newlines.
std::string one_line(std::string text) {
  std::replace_if(
      text.begin(), text.end(), [](char c) { return c == '\n' || c == '\r'; }, ' ');
  while (!text.empty() && std::isspace(static_cast<unsigned char>(text.back()))) text.pop_back();
  return text;
}

[[noreturn]] void fail(const fs::path& file, const std::string& defect) {
  throw MeshError("mesh '" + file.string() + "': " + one_line(defect));
}

// std::to_string(double) prints fixed 6 decimals, which turns 1e-9 into "0.000000".
using detail::format_number;
using detail::format_point;

std::string lower_extension(const fs::path& file) {
  std::string ext = file.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return ext;
}

// assimp 5.2's PLY reader loops forever (found by fuzz_mesh) when the header never ends or an
// element line has no count, and reserves memory for whatever count it parses, so the header's
// grammar is checked before assimp sees the file: every line is a comment, obj_info, format,
// element or property line, element names are names (assimp parses an unknown name that starts
// with digits as the count: fuzz_mesh found "element 666...6vertex 8" asking for 64 GiB), and
// the counts fit in the file. The header is ASCII in every PLY variant; the body is left to
// assimp (whose runaway allocations on it the child process of load_mesh bounds).
void check_ply_header(const fs::path& file) {
  std::error_code ec;
  const std::uintmax_t size = fs::file_size(file, ec);
  std::ifstream in(file, std::ios::binary);
  if (ec || !in) return;  // let assimp report the I/O problem in its own words
  std::string line;
  // assimp takes the magic number in any case ("plY" too: fuzz_mesh found it looping on one).
  if (!std::getline(in, line) || line.size() < 3) return;
  std::string magic = line.substr(0, 3);
  std::transform(magic.begin(), magic.end(), magic.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  if (magic != "ply") return;  // not a PLY: assimp decides
  const auto is_name = [](const std::string& word) {
    return !word.empty() &&
           (std::isalpha(static_cast<unsigned char>(word[0])) != 0 || word[0] == '_') &&
           std::all_of(word.begin(), word.end(), [](unsigned char c) {
             return std::isalnum(c) != 0 || c == '_' || c == '-' || c == '.';
           });
  };
  const auto is_type = [](const std::string& word) {
    static const std::array<std::string_view, 16> types = {
        "char", "uchar", "short", "ushort", "int",   "uint",   "float",   "double",
        "int8", "uint8", "int16", "uint16", "int32", "uint32", "float32", "float64"};
    return std::find(types.begin(), types.end(), word) != types.end();
  };
  bool has_element = false;
  for (int number = 2; std::getline(in, line); ++number) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line == "end_header") return;
    std::istringstream words(line);
    std::string keyword;
    words >> keyword;
    const auto malformed = [&](const std::string& expected) {
      fail(file, "PLY header line " + std::to_string(number) + " is not '" + expected +
                     "' (a malformed file)");
    };
    if (keyword.empty() || keyword == "comment" || keyword == "obj_info" || keyword == "format") {
      continue;
    }
    if (keyword == "element") {
      std::string name, count, extra;
      words >> name >> count;
      const bool counted =
          !count.empty() && count.find_first_not_of("0123456789") == std::string::npos;
      if (!is_name(name) || !counted || (words >> extra)) malformed("element <name> <count>");
      // Every element takes at least a byte of the body (assimp reserves memory for the count
      // first: 35 digits of it were found by fuzz_mesh).
      if (count.size() > 18 || std::stoull(count) > size) {
        fail(file, "PLY header line " + std::to_string(number) + " announces " + count + " '" +
                       name + "' elements, more than the file's " + std::to_string(size) +
                       " bytes can hold (a malformed file)");
      }
      has_element = true;
    } else if (keyword == "property") {
      std::string type, name, extra;
      words >> type;
      bool ok = has_element;
      if (type == "list") {
        std::string count_type, item_type;
        words >> count_type >> item_type;
        ok = ok && is_type(count_type) && is_type(item_type);
      } else {
        ok = ok && is_type(type);
      }
      words >> name;
      if (!ok || !is_name(name) || (words >> extra)) {
        malformed(
            "property <type> <name>' or 'property list <type> <type> <name>' after an "
            "'element");
      }
    } else {
      fail(file, "PLY header line " + std::to_string(number) + " ('" + line.substr(0, 24) +
                     "') is not a header line and no end_header came before it (a malformed or "
                     "truncated file)");
    }
  }
  fail(file, "PLY header has no end_header line (a malformed or truncated file)");
}

// assimp only says "Failed to determine STL storage representation" for a truncated binary STL,
// which does not tell the user what is wrong. A binary STL is an 80-byte header, a uint32
// triangle count and 50 bytes per triangle; assimp treats a file starting with "solid" as ASCII
// unless its size matches that layout, so only files that cannot be ASCII are checked here.
void check_binary_stl_size(const fs::path& file) {
  std::error_code ec;
  const std::uintmax_t size = fs::file_size(file, ec);
  std::ifstream in(file, std::ios::binary);
  if (ec || !in) return;  // let assimp report the I/O problem in its own words
  std::array<char, 84> head{};
  in.read(head.data(), head.size());
  const auto got = static_cast<std::size_t>(in.gcount());
  std::size_t first = 0;
  while (first < got && std::isspace(static_cast<unsigned char>(head[first]))) ++first;
  if (got - first >= 5 && std::string_view(head.data() + first, 5) == "solid") return;
  if (size < 84) {
    fail(file, "binary STL is " + std::to_string(size) +
                   " bytes, too short for the 84-byte header (truncated?)");
  }
  std::uint32_t count = 0;
  for (int b = 3; b >= 0; --b) count = (count << 8) | static_cast<unsigned char>(head[80 + b]);
  const std::uintmax_t expected = 84 + 50 * static_cast<std::uintmax_t>(count);
  if (size != expected) {
    fail(file, "binary STL header announces " + std::to_string(count) + " triangles (" +
                   std::to_string(expected) + " bytes) but the file has " + std::to_string(size) +
                   (size < expected ? " bytes (truncated?)" : " bytes"));
  }
}

Eigen::Matrix4d to_eigen(const aiMatrix4x4& m) {
  Eigen::Matrix4d e;
  e << m.a1, m.a2, m.a3, m.a4, m.b1, m.b2, m.b3, m.b4, m.c1, m.c2, m.c3, m.c4, m.d1, m.d2, m.d3,
      m.d4;
  return e;
}

Eigen::Affine3d placement(const ImportOptions& options) {
  Eigen::Affine3d t = Eigen::Affine3d::Identity();
  t.linear() = rotation_from_degrees(options.rotation_deg) * options.scale;
  t.translation() = options.translation;
  return t;
}

// Non-finite values are rejected before any post-processing step sees them: assimp's vertex
// joining sorts and compares positions, which is meaningless for NaN. Indices here are those of
// the file as assimp parsed it, which is the numbering closest to what the user can look up.
void check_finite(const aiScene& scene, const fs::path& file) {
  for (unsigned m = 0; m < scene.mNumMeshes; ++m) {
    const aiMesh& mesh = *scene.mMeshes[m];
    if (mesh.mVertices == nullptr) continue;
    for (unsigned v = 0; v < mesh.mNumVertices; ++v) {
      const aiVector3D& p = mesh.mVertices[v];
      if (std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z)) continue;
      std::string where = "vertex " + std::to_string(v);
      if (scene.mNumMeshes > 1) {
        where += " of sub-mesh " + std::to_string(m);
        if (mesh.mName.length > 0) where += " '" + std::string(mesh.mName.C_Str()) + "'";
      }
      fail(file, where + " has a non-finite coordinate " + format_point({p.x, p.y, p.z}));
    }
  }
}

// Faces assimp's parser produced but its validation lets through, on which its triangulation
// aborts the process (an assertion in assimp 5.2, found by fuzz_mesh): a face without vertices,
// or one whose size the mesh's primitive flags do not announce.
void check_faces(const aiScene& scene, const fs::path& file) {
  for (unsigned m = 0; m < scene.mNumMeshes; ++m) {
    const aiMesh& mesh = *scene.mMeshes[m];
    for (unsigned f = 0; f < mesh.mNumFaces; ++f) {
      const unsigned n = mesh.mFaces[f].mNumIndices;
      const unsigned type = n == 1   ? aiPrimitiveType_POINT
                            : n == 2 ? aiPrimitiveType_LINE
                            : n == 3 ? aiPrimitiveType_TRIANGLE
                                     : aiPrimitiveType_POLYGON;
      if (n > 0 && (mesh.mPrimitiveTypes & type) != 0) continue;
      std::string where = "face " + std::to_string(f);
      if (scene.mNumMeshes > 1) where += " of sub-mesh " + std::to_string(m);
      fail(file, where + (n == 0 ? " has no vertices" : " does not match the file's face types") +
                     " (a malformed file)");
    }
  }
}

// Triangles of every mesh instance, in the output frame, before welding.
struct Soup {
  std::vector<Eigen::Vector3d> points;
  std::vector<std::array<std::size_t, 3>> faces;
  std::vector<int> face_part;
  std::vector<std::string> part_names;
  std::unordered_map<std::string, int> part_of_name;
};

int part_index(Soup& soup, const aiMesh& mesh, const aiNode& node) {
  std::string name = mesh.mName.C_Str();
  if (name.empty()) name = node.mName.C_Str();
  if (name.empty()) name = "part" + std::to_string(soup.part_names.size());
  const auto [it, inserted] = soup.part_of_name.try_emplace(name, soup.part_names.size());
  if (inserted) soup.part_names.push_back(name);
  return it->second;
}

void append_instance(const aiMesh& mesh, const aiNode& node, const Eigen::Affine3d& to_output,
                     const fs::path& file, Soup& soup, ImportReport& report) {
  std::size_t triangles = 0;
  for (unsigned f = 0; f < mesh.mNumFaces; ++f) triangles += mesh.mFaces[f].mNumIndices == 3;
  report.skipped_primitives += mesh.mNumFaces - triangles;
  if (triangles == 0 || mesh.mVertices == nullptr) return;

  const int part = part_index(soup, mesh, node);
  const std::size_t base = soup.points.size();
  for (unsigned v = 0; v < mesh.mNumVertices; ++v) {
    const aiVector3D& p = mesh.mVertices[v];
    const Eigen::Vector3d q = to_output * Eigen::Vector3d(p.x, p.y, p.z);
    if (!q.allFinite()) {
      fail(file, "vertex " + std::to_string(v) + " " + format_point({p.x, p.y, p.z}) +
                     " becomes non-finite under the node transform, scale and rotation");
    }
    soup.points.push_back(q);
  }
  // A mirroring transform turns counter-clockwise into clockwise; swapping two corners keeps
  // the faces pointing outwards.
  const bool flip = to_output.linear().determinant() < 0.0;
  for (unsigned f = 0; f < mesh.mNumFaces; ++f) {
    const aiFace& face = mesh.mFaces[f];
    if (face.mNumIndices != 3) continue;
    for (unsigned k = 0; k < 3; ++k) {
      if (face.mIndices[k] >= mesh.mNumVertices) {
        fail(file, "face " + std::to_string(f) + " references vertex " +
                       std::to_string(face.mIndices[k]) + " of " +
                       std::to_string(mesh.mNumVertices));
      }
    }
    std::array<std::size_t, 3> t{base + face.mIndices[0], base + face.mIndices[1],
                                 base + face.mIndices[2]};
    if (flip) std::swap(t[1], t[2]);
    soup.faces.push_back(t);
    soup.face_part.push_back(part);
  }
  report.input_vertices += mesh.mNumVertices;
  report.input_triangles += triangles;
}

// Walks the node tree iteratively (files can nest deeply) and instantiates every mesh a node
// references with the node's global transform, as aiProcess_PreTransformVertices would; that
// step is not used because it merges meshes sharing a material and so loses the part names.
Soup collect(const aiScene& scene, const ImportOptions& options, const fs::path& file,
             ImportReport& report) {
  Soup soup;
  const Eigen::Affine3d to_output = placement(options);
  std::vector<std::pair<const aiNode*, Eigen::Matrix4d>> stack;
  if (scene.mRootNode) stack.emplace_back(scene.mRootNode, Eigen::Matrix4d::Identity());
  while (!stack.empty()) {
    const auto [node, parent] = stack.back();
    stack.pop_back();
    const Eigen::Matrix4d global = parent * to_eigen(node->mTransformation);
    const Eigen::Affine3d instance = to_output * Eigen::Affine3d(global);
    for (unsigned i = 0; i < node->mNumMeshes; ++i) {
      if (node->mMeshes[i] >= scene.mNumMeshes) continue;  // ValidateDS rejects this already
      append_instance(*scene.mMeshes[node->mMeshes[i]], *node, instance, file, soup, report);
    }
    // Reverse order so that children are visited in file order.
    for (unsigned c = node->mNumChildren; c-- > 0;) stack.emplace_back(node->mChildren[c], global);
  }
  return soup;
}

using CellKey = std::array<std::int64_t, 3>;

struct CellKeyHash {
  std::size_t operator()(const CellKey& k) const noexcept {
    // splitmix64 finaliser: cheap and scrambles neighbouring cells well.
    auto mix = [](std::uint64_t x) {
      x += 0x9e3779b97f4a7c15ULL;
      x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
      x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
      return x ^ (x >> 31);
    };
    std::uint64_t h = mix(static_cast<std::uint64_t>(k[0]));
    h = mix(h ^ static_cast<std::uint64_t>(k[1]));
    return static_cast<std::size_t>(mix(h ^ static_cast<std::uint64_t>(k[2])));
  }
};

// Maps every point to a representative, returned in `welded`. Greedy: a point joins the first
// earlier representative within `tolerance`, else it becomes one. Representatives live in a
// hash grid with cells of 2 * tolerance, so a point only has to look at its own cell and, per
// axis, the one neighbour on the side of the cell it is closer to (8 cells instead of 27).
std::vector<std::size_t> weld(const std::vector<Eigen::Vector3d>& points, double tolerance,
                              std::vector<Eigen::Vector3d>& welded) {
  std::vector<std::size_t> representative(points.size());
  welded.clear();
  std::unordered_map<CellKey, std::size_t, CellKeyHash> head;
  std::vector<std::size_t> next;  // chain of representatives sharing a cell
  constexpr std::size_t none = std::numeric_limits<std::size_t>::max();
  head.reserve(points.size());

  Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  Eigen::Vector3d hi = -lo;
  for (const auto& p : points) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  const double cell = 2.0 * tolerance;
  // Beyond ~1e15 cells per axis the integer cell coordinates lose meaning (and would overflow
  // for absurd tolerances); the tolerance is then below double resolution anyway, so weld
  // exact positions, keyed by their bit patterns.
  const bool exact = !(cell > 0.0) || (hi - lo).maxCoeff() / cell > 1e15;

  const double tol2 = tolerance * tolerance;
  for (std::size_t i = 0; i < points.size(); ++i) {
    const Eigen::Vector3d& p = points[i];
    CellKey key;
    // Per axis the cell offsets to visit: always 0, plus the neighbour on the nearer side
    // (both only when the point sits exactly in the middle).
    std::array<std::array<int, 3>, 3> offsets{};
    std::array<int, 3> n_offsets{1, 1, 1};
    if (exact) {
      // "+ 0.0" turns -0.0 into +0.0 so both signs of zero weld.
      for (int a = 0; a < 3; ++a) key[a] = std::bit_cast<std::int64_t>(p[a] + 0.0);
    } else {
      for (int a = 0; a < 3; ++a) {
        const double q = (p[a] - lo[a]) / cell;
        const double c = std::floor(q);
        key[a] = static_cast<std::int64_t>(c);
        const double frac = q - c;
        if (frac <= 0.5) offsets[a][n_offsets[a]++] = -1;
        if (frac >= 0.5) offsets[a][n_offsets[a]++] = 1;
      }
    }
    std::size_t found = none;
    // Own cell first (offsets start with 0), stopping at the first representative in reach.
    for (int x = 0; x < n_offsets[0] && found == none; ++x) {
      for (int y = 0; y < n_offsets[1] && found == none; ++y) {
        for (int z = 0; z < n_offsets[2] && found == none; ++z) {
          const auto it =
              head.find({key[0] + offsets[0][x], key[1] + offsets[1][y], key[2] + offsets[2][z]});
          if (it == head.end()) continue;
          for (std::size_t r = it->second; r != none; r = next[r]) {
            if ((welded[r] - p).squaredNorm() <= tol2) {
              found = r;
              break;
            }
          }
        }
      }
    }
    if (found == none) {
      found = welded.size();
      welded.push_back(p);
      auto [it, inserted] = head.try_emplace(key, found);
      next.push_back(inserted ? none : it->second);
      it->second = found;
    }
    representative[i] = found;
  }
  return representative;
}

TriangleMesh build(const Soup& soup, const ImportOptions& options, const fs::path& file,
                   ImportReport& report) {
  if (soup.faces.empty()) {
    fail(file, report.skipped_primitives > 0
                   ? "contains no triangles (only " + std::to_string(report.skipped_primitives) +
                         " points or lines)"
                   : "contains no triangles");
  }
  double tolerance = options.weld_tolerance;
  if (tolerance == 0.0) {
    Eigen::AlignedBox3d box;
    for (const auto& p : soup.points) box.extend(p);
    tolerance = 1e-9 * box.diagonal().norm();
  }
  report.weld_tolerance = tolerance;

  std::vector<Eigen::Vector3d> welded;
  const std::vector<std::size_t> rep = weld(soup.points, tolerance, welded);

  // Keep faces whose three corners stay distinct; renumber the vertices and parts they use, in
  // order of first appearance in the representatives / part list, so nothing unreferenced is
  // returned.
  constexpr std::size_t unused = std::numeric_limits<std::size_t>::max();
  std::vector<std::array<std::size_t, 3>> faces;
  std::vector<int> face_part;
  faces.reserve(soup.faces.size());
  face_part.reserve(soup.faces.size());
  std::vector<std::size_t> new_vertex(welded.size(), unused);
  std::vector<int> new_part(soup.part_names.size(), -1);
  for (std::size_t f = 0; f < soup.faces.size(); ++f) {
    const std::array<std::size_t, 3> t{rep[soup.faces[f][0]], rep[soup.faces[f][1]],
                                       rep[soup.faces[f][2]]};
    if (t[0] == t[1] || t[1] == t[2] || t[0] == t[2]) {
      ++report.dropped_degenerate_faces;
      continue;
    }
    for (std::size_t v : t) new_vertex[v] = 0;  // mark as used; numbered below
    new_part[soup.face_part[f]] = 0;
    faces.push_back(t);
    face_part.push_back(soup.face_part[f]);
  }
  if (faces.empty()) {
    fail(file, "contains no triangles with three distinct vertices (all " +
                   std::to_string(soup.faces.size()) + " are degenerate after welding at " +
                   format_number(tolerance) + ")");
  }

  std::size_t vertex_count = 0;
  for (auto& v : new_vertex) {
    if (v != unused) v = vertex_count++;
  }
  if (vertex_count > static_cast<std::size_t>(std::numeric_limits<int>::max()) ||
      faces.size() > static_cast<std::size_t>(std::numeric_limits<int>::max())) {
    fail(file, "too large for int indices (" + std::to_string(vertex_count) + " vertices, " +
                   std::to_string(faces.size()) + " faces)");
  }

  TriangleMesh mesh;
  mesh.V.resize(static_cast<Eigen::Index>(vertex_count), 3);
  for (std::size_t v = 0; v < welded.size(); ++v) {
    if (new_vertex[v] != unused) mesh.V.row(static_cast<Eigen::Index>(new_vertex[v])) = welded[v];
  }
  int part_count = 0;
  for (std::size_t p = 0; p < new_part.size(); ++p) {
    if (new_part[p] < 0) continue;
    new_part[p] = part_count++;
    mesh.part_names.push_back(soup.part_names[p]);
  }
  mesh.F.resize(static_cast<Eigen::Index>(faces.size()), 3);
  mesh.part.resize(static_cast<Eigen::Index>(faces.size()));
  for (std::size_t f = 0; f < faces.size(); ++f) {
    const auto row = static_cast<Eigen::Index>(f);
    for (int k = 0; k < 3; ++k) mesh.F(row, k) = static_cast<int>(new_vertex[faces[f][k]]);
    mesh.part(row) = new_part[face_part[f]];
  }
  return mesh;
}

}  // namespace

bool ImportOptions::valid(std::string* why) const {
  auto no = [why](const char* reason) {
    if (why) *why = reason;
    return false;
  };
  if (!std::isfinite(scale) || !(scale > 0.0)) return no("scale must be finite and positive");
  if (!translation.allFinite()) return no("translation must be finite");
  if (!rotation_deg.allFinite()) return no("rotation_deg must be finite");
  if (!std::isfinite(weld_tolerance) || weld_tolerance < 0.0) {
    return no("weld_tolerance must be finite and non-negative (0 = automatic)");
  }
  return true;
}

namespace {

// What assimp gives, turned into a triangle soup in the output frame (checks included).
void read_soup(const fs::path& file, const ImportOptions& options, Soup& soup,
               ImportReport& report) {
  Assimp::Importer importer;
  // Normals, colours and UVs would keep assimp from joining vertices that only differ in them
  // (every STL corner has its own face normal); only positions matter here.
  importer.SetPropertyInteger(AI_CONFIG_PP_RVC_FLAGS,
                              aiComponent_NORMALS | aiComponent_TANGENTS_AND_BITANGENTS |
                                  aiComponent_COLORS | aiComponent_TEXCOORDS |
                                  aiComponent_BONEWEIGHTS | aiComponent_ANIMATIONS |
                                  aiComponent_TEXTURES | aiComponent_LIGHTS | aiComponent_CAMERAS);
  // Read and validate first, check positions, then post-process (see check_finite).
  // aiProcess_FindInvalidData stays off: it would drop a mesh with NaN positions silently.
  const aiScene* scene = importer.ReadFile(file.string(), aiProcess_ValidateDataStructure);
  if (scene == nullptr) {
    fail(file, std::string("assimp cannot read it: ") + importer.GetErrorString());
  }
  check_finite(*scene, file);
  check_faces(*scene, file);
  scene = importer.ApplyPostProcessing(aiProcess_RemoveComponent | aiProcess_Triangulate |
                                       aiProcess_JoinIdenticalVertices);
  if (scene == nullptr) {
    fail(file, std::string("assimp post-processing failed: ") + importer.GetErrorString());
  }
  soup = collect(*scene, options, file, report);
}

// ---- The import in a child process ------------------------------------------------------
// assimp parses untrusted files, and fuzz_mesh keeps finding inputs on which it asserts, loops
// or allocates without bound: an ASCII PLY face announcing 3.4e9 indices grew `mpm prep` to
// 24 GB until the kernel killed it. So the parsing runs in a forked child that sends the soup
// back through a pipe; the parent kills it when its resident memory or its run time passes a
// budget, and every way the child can end other than with a soup becomes a MeshError naming the
// file. Welding (build) stays in the parent: it is ours and bounded by the soup's size.

struct Limits {
  std::uint64_t memory_bytes;
  double seconds;  ///< of the child's CPU time
  /// Of wall-clock time: for a reader that waits without computing (a FIFO given as the mesh).
  double wall_seconds;
};

// Generous for real meshes (assimp needs ~10-20 bytes of memory per byte of STL, and reads
// ~100 MB/s: 20 s + 1 s per MB is 10-100 times what it takes), tight enough that a pathological
// file fails in seconds, not after swapping (a hang in a small file waited 120 s before); never
// more than 3/4 of the machine's memory, so that the budget, not the kernel, stops the reader.
// The time is the child's CPU time, not the wall clock: on a loaded machine (the sanitizer
// build's test suite, two tests at a time) the 0.6 MB terrain took more than 20 s of wall clock
// to read and a valid scene was refused; its CPU time is a few seconds whatever the load. The
// wall clock only backs it up, at ten times as much.
Limits limits_for(const fs::path& file, std::uint64_t memory_budget_bytes) {
  std::error_code ec;
  const double size = static_cast<double>(fs::file_size(file, ec));
  const double bytes = ec ? 0.0 : size;
  const double physical =
      static_cast<double>(::sysconf(_SC_PHYS_PAGES)) * static_cast<double>(::sysconf(_SC_PAGESIZE));
  double memory = memory_budget_bytes > 0 ? static_cast<double>(memory_budget_bytes)
                                          : std::max(4.0 * (1ull << 30), 64.0 * bytes);
  if (physical > 0.0) memory = std::min(memory, 0.75 * physical);
  const double seconds = 20.0 + bytes / 1e6;
  return {static_cast<std::uint64_t>(memory), seconds, 10.0 * seconds};
}

void write_all(int fd, const void* data, std::size_t n) {
  const char* p = static_cast<const char*>(data);
  while (n > 0) {
    const ssize_t w = ::write(fd, p, n);
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) ::_exit(3);  // the parent is gone or gave up on us
    p += w;
    n -= static_cast<std::size_t>(w);
  }
}

void write_u64(int fd, std::uint64_t v) { write_all(fd, &v, sizeof v); }

// Child: one status byte, then the soup and the report ('S') or a one-line message ('E').
[[noreturn]] void child_import(int fd, const fs::path& file, const ImportOptions& options) {
  std::string error;
  try {
    Soup soup;
    ImportReport report;
    read_soup(file, options, soup, report);
    write_all(fd, "S", 1);
    for (std::uint64_t v :
         {std::uint64_t(report.input_vertices), std::uint64_t(report.input_triangles),
          std::uint64_t(report.skipped_primitives)}) {
      write_u64(fd, v);
    }
    write_u64(fd, soup.points.size());
    write_all(fd, soup.points.data(), soup.points.size() * sizeof(Eigen::Vector3d));
    write_u64(fd, soup.faces.size());
    write_all(fd, soup.faces.data(), soup.faces.size() * sizeof(soup.faces[0]));
    write_all(fd, soup.face_part.data(), soup.face_part.size() * sizeof(int));
    write_u64(fd, soup.part_names.size());
    for (const std::string& name : soup.part_names) {
      write_u64(fd, name.size());
      write_all(fd, name.data(), name.size());
    }
    ::_exit(0);
  } catch (const MeshError& e) {
    error = e.what();
  } catch (const std::bad_alloc&) {
    error = "mesh '" + file.string() + "': ran out of memory while reading it";
  } catch (const std::exception& e) {
    error = "mesh '" + file.string() + "': cannot read it: " + one_line(e.what());
  }
  write_all(fd, "E", 1);
  write_all(fd, error.data(), error.size());
  ::_exit(0);  // no atexit handlers, no flushing of the parent's buffers, no leak check
}

// A process's resident memory and its user + system CPU time so far, from one read of
// /proc/PID/stat (proc(5): fields 14, 15 and 24, counted after the command name, which is in
// parentheses and may hold spaces); zeros if unknown.
struct Usage {
  std::uint64_t resident_bytes = 0;
  double cpu_seconds = 0.0;
};

Usage usage_of(pid_t pid) {
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string line;
  std::getline(stat, line);
  const std::size_t close = line.rfind(')');
  if (close == std::string::npos) return {};
  std::istringstream fields(line.substr(close + 1));
  std::string skip;
  for (int field = 3; field <= 13; ++field) fields >> skip;  // state ... cmajflt
  double user = 0.0, system = 0.0;
  fields >> user >> system;
  for (int field = 16; field <= 23; ++field) fields >> skip;  // cutime ... vsize
  std::uint64_t pages = 0;
  fields >> pages;
  return {pages * static_cast<std::uint64_t>(::sysconf(_SC_PAGESIZE)),
          (user + system) / static_cast<double>(::sysconf(_SC_CLK_TCK))};
}

// Parent: reads what the child sends, watching its memory and run time.
class ChildReader {
 public:
  ChildReader(pid_t pid, int fd, const fs::path& file, Limits limits)
      : pid_(pid),
        fd_(fd),
        file_(file),
        limits_(limits),
        start_(std::chrono::steady_clock::now()) {}
  ChildReader(const ChildReader&) = delete;
  ChildReader& operator=(const ChildReader&) = delete;
  ~ChildReader() {
    ::close(fd_);
    if (!reaped_) {
      ::kill(pid_, SIGKILL);
      reap();
    }
  }

  // Up to n bytes as they arrive (0 at the end of the stream: the child exited or died),
  // watching the child's memory and run time while it waits.
  std::size_t some(void* data, std::size_t n) {
    for (;;) {
      pollfd pfd{fd_, POLLIN, 0};
      const int ready = ::poll(&pfd, 1, 20);
      watch();
      if (ready < 0 && errno != EINTR) fail(file_, "cannot wait for the mesh importer");
      if (ready <= 0) continue;
      const ssize_t r = ::read(fd_, data, n);
      if (r < 0 && errno == EINTR) continue;
      return r > 0 ? static_cast<std::size_t>(r) : 0;
    }
  }

  // Exactly n bytes; the stream ending before them is the child's failure.
  void exact(void* data, std::size_t n) {
    char* p = static_cast<char*>(data);
    while (n > 0) {
      const std::size_t got = some(p, n);
      if (got == 0) died("stopped in the middle of its answer");
      p += got;
      n -= got;
    }
  }

  std::uint64_t u64() {
    std::uint64_t v = 0;
    exact(&v, sizeof v);
    return v;
  }

  // A count from the child, bounded by what the memory budget could have held.
  std::size_t count(std::size_t item_bytes) {
    const std::uint64_t n = u64();
    if (n > limits_.memory_bytes / item_bytes) died("sent an impossible size");
    return static_cast<std::size_t>(n);
  }

  std::string rest() {
    std::string text;
    char buffer[4096];
    while (const std::size_t got = some(buffer, sizeof buffer)) text.append(buffer, got);
    return text;
  }

  // Waits for the child's exit; a clean exit is the only good end.
  void finish() {
    const int status = reap();
    if (!(WIFEXITED(status) && WEXITSTATUS(status) == 0)) died("failed");
  }

  [[noreturn]] void died(const std::string& what) {
    const int status = reaped_ ? status_ : (::kill(pid_, SIGKILL), reap());
    std::string how = "the mesh importer (assimp) " + what;
    if (WIFSIGNALED(status)) {
      how += " (signal " + std::to_string(WTERMSIG(status)) + ")";
    } else if (WIFEXITED(status) && WEXITSTATUS(status) != 0) {
      how += " (exit " + std::to_string(WEXITSTATUS(status)) + ")";
    }
    fail(file_, how + " reading it: a malformed or unsupported file?");
  }

 private:
  void watch() {
    const Usage usage = usage_of(pid_);
    if (usage.resident_bytes > limits_.memory_bytes) {
      stop("reading it took more than " + std::to_string(limits_.memory_bytes >> 20) +
           " MiB of memory (a malformed file announcing huge counts?); stopped");
    }
    if (usage.cpu_seconds > limits_.seconds) {
      stop("reading it took more than " + format_number(limits_.seconds) +
           " s of CPU time (a malformed file that makes the reader loop?); stopped");
    }
    const double elapsed =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
    if (elapsed > limits_.wall_seconds) {
      stop("reading it took more than " + format_number(limits_.wall_seconds) +
           " s (a reader waiting for input that never comes?); stopped");
    }
  }

  [[noreturn]] void stop(const std::string& why) {
    ::kill(pid_, SIGKILL);
    reap();
    fail(file_, why);
  }

  int reap() {
    if (reaped_) return status_;
    while (::waitpid(pid_, &status_, 0) < 0 && errno == EINTR) {
    }
    reaped_ = true;
    return status_;
  }

  pid_t pid_;
  int fd_;
  fs::path file_;
  Limits limits_;
  std::chrono::steady_clock::time_point start_;
  bool reaped_ = false;
  int status_ = 0;
};

void read_soup_isolated(const fs::path& file, const ImportOptions& options, Soup& soup,
                        ImportReport& report) {
  int fds[2];
  if (::pipe2(fds, O_CLOEXEC) != 0) fail(file, "cannot start the mesh importer (pipe)");
  const pid_t pid = ::fork();
  if (pid < 0) {
    ::close(fds[0]);
    ::close(fds[1]);
    fail(file, "cannot start the mesh importer (fork)");
  }
  if (pid == 0) {
    ::close(fds[0]);
    child_import(fds[1], file, options);
  }
  ::close(fds[1]);
  ChildReader in(pid, fds[0], file, limits_for(file, options.memory_budget_bytes));
  char status = 0;
  if (in.some(&status, 1) == 0) {
    in.finish();
    in.died("ended without an answer");
  }
  if (status == 'E') {
    const std::string message = in.rest();
    in.finish();
    throw MeshError(message);
  }
  if (status != 'S') in.died("sent a malformed answer");
  report.input_vertices = in.u64();
  report.input_triangles = in.u64();
  report.skipped_primitives = in.u64();
  soup.points.resize(in.count(sizeof(Eigen::Vector3d)));
  in.exact(soup.points.data(), soup.points.size() * sizeof(Eigen::Vector3d));
  soup.faces.resize(in.count(sizeof(soup.faces[0]) + sizeof(int)));
  soup.face_part.resize(soup.faces.size());
  in.exact(soup.faces.data(), soup.faces.size() * sizeof(soup.faces[0]));
  in.exact(soup.face_part.data(), soup.face_part.size() * sizeof(int));
  // Part names only: the name -> index map serves collect(), in the child.
  soup.part_names.resize(in.count(sizeof(std::uint64_t)));
  for (std::string& name : soup.part_names) {
    name.resize(in.count(1));
    in.exact(name.data(), name.size());
  }
  const std::size_t parts = soup.part_names.size();
  in.finish();
  // The child checked these; a soup that breaks them did not come from it.
  for (std::size_t f = 0; f < soup.faces.size(); ++f) {
    for (std::size_t v : soup.faces[f]) {
      if (v >= soup.points.size()) in.died("sent a malformed answer");
    }
    if (soup.face_part[f] < 0 || static_cast<std::size_t>(soup.face_part[f]) >= parts) {
      in.died("sent a malformed answer");
    }
  }
}

}  // namespace

TriangleMesh load_mesh(const fs::path& file, const ImportOptions& options, ImportReport* report) {
  std::string why;
  if (!options.valid(&why)) fail(file, "invalid import options: " + why);
  std::error_code ec;
  if (!fs::exists(file, ec)) fail(file, "file does not exist");
  if (!fs::is_regular_file(file, ec)) fail(file, "is not a regular file");
  if (lower_extension(file) == ".stl") check_binary_stl_size(file);
  check_ply_header(file);

  ImportReport local;
  ImportReport& rep = report ? *report : local;
  rep = ImportReport{};
  Soup soup;
  if (options.isolate) {
    read_soup_isolated(file, options, soup, rep);
  } else {
    read_soup(file, options, soup, rep);
  }
  return build(soup, options, file, rep);
}

void save_mesh(const TriangleMesh& mesh, const fs::path& file, const SaveOptions& options) {
  const Eigen::Index nv = mesh.V.rows();
  const Eigen::Index nf = mesh.F.rows();
  if (nf == 0) fail(file, "nothing to write: the mesh has no faces");
  if (mesh.part.size() != 0 && mesh.part.size() != nf) {
    fail(file, "part has " + std::to_string(mesh.part.size()) + " entries for " +
                   std::to_string(nf) + " faces");
  }
  if (!mesh.V.allFinite()) fail(file, "a vertex position is not finite");
  for (Eigen::Index f = 0; f < nf; ++f) {
    for (int k = 0; k < 3; ++k) {
      if (mesh.F(f, k) < 0 || mesh.F(f, k) >= nv) {
        fail(file, "face " + std::to_string(f) + " references vertex " +
                       std::to_string(mesh.F(f, k)) + " of " + std::to_string(nv));
      }
    }
    if (mesh.part.size() != 0 &&
        (mesh.part(f) < 0 || static_cast<std::size_t>(mesh.part(f)) >= mesh.part_names.size())) {
      fail(file, "face " + std::to_string(f) + " has part " + std::to_string(mesh.part(f)) +
                     " of " + std::to_string(mesh.part_names.size()));
    }
  }

  const std::string ext = lower_extension(file);
  std::string format;
  if (ext == ".stl") {
    format = options.binary ? "stlb" : "stl";
  } else if (ext == ".ply") {
    format = options.binary ? "plyb" : "ply";
  } else if (ext == ".obj") {
    format = "objnomtl";  // no .mtl next to it: geometry files should be one file
  } else {
    fail(file, "cannot write extension '" + ext + "' (use .stl, .obj or .ply)");
  }

  // Without a part vector every face belongs to one part.
  std::vector<std::string> names = mesh.part_names;
  if (mesh.part.size() == 0) names.assign(1, names.empty() ? "mesh" : names.front());
  auto part_of = [&](Eigen::Index f) { return mesh.part.size() == 0 ? 0 : mesh.part(f); };

  // STL and OBJ get one vertex per face corner, carrying the face normal. Left to themselves,
  // assimp's exporters generate normals: the STL one face normals on shared vertices (the last
  // face sharing a vertex wins, so most facets get a wrong normal), the OBJ one smoothed vertex
  // normals. The OBJ writer merges equal positions and normals again, so its file stays
  // indexed. PLY keeps shared vertices and has no normals.
  const bool per_corner = format != "ply" && format != "plyb";
  if (static_cast<std::uintmax_t>(per_corner ? 3 * nf : nv) >
      std::numeric_limits<unsigned>::max()) {
    fail(file, "too large for assimp's unsigned indices");
  }
  auto to_ai = [](const Eigen::Vector3d& p) {
    return aiVector3D(static_cast<ai_real>(p.x()), static_cast<ai_real>(p.y()),
                      static_cast<ai_real>(p.z()));
  };

  // One aiMesh and node per non-empty part; the aiScene destructor frees everything allocated
  // below.
  auto scene = std::make_unique<aiScene>();
  if (!per_corner) scene->mFlags |= AI_SCENE_FLAGS_NON_VERBOSE_FORMAT;
  scene->mRootNode = new aiNode(file.stem().string());
  scene->mMaterials = new aiMaterial*[1];
  scene->mMaterials[0] = new aiMaterial();
  scene->mNumMaterials = 1;
  const aiString material_name("default");
  scene->mMaterials[0]->AddProperty(&material_name, AI_MATKEY_NAME);

  std::vector<std::vector<Eigen::Index>> faces_of(names.size());
  for (Eigen::Index f = 0; f < nf; ++f) faces_of[static_cast<std::size_t>(part_of(f))].push_back(f);
  std::vector<std::size_t> used;
  for (std::size_t p = 0; p < names.size(); ++p) {
    if (!faces_of[p].empty()) used.push_back(p);
  }
  const auto count = static_cast<unsigned>(used.size());
  scene->mMeshes = new aiMesh*[count]();
  scene->mNumMeshes = count;
  scene->mRootNode->mChildren = new aiNode*[count]();
  scene->mRootNode->mNumChildren = count;

  std::vector<unsigned> local(static_cast<std::size_t>(nv), 0);  // indexed case: 1 + new index
  for (unsigned m = 0; m < count; ++m) {
    const std::vector<Eigen::Index>& faces = faces_of[used[m]];
    auto* out = new aiMesh();
    scene->mMeshes[m] = out;
    out->mName = aiString(names[used[m]]);
    out->mMaterialIndex = 0;
    out->mPrimitiveTypes = aiPrimitiveType_TRIANGLE;
    out->mNumFaces = static_cast<unsigned>(faces.size());
    out->mFaces = new aiFace[faces.size()];
    for (aiFace* face = out->mFaces; face != out->mFaces + faces.size(); ++face) {
      face->mNumIndices = 3;
      face->mIndices = new unsigned[3];
    }

    if (per_corner) {
      out->mNumVertices = static_cast<unsigned>(3 * faces.size());
      out->mVertices = new aiVector3D[3 * faces.size()];
      out->mNormals = new aiVector3D[3 * faces.size()];
      for (std::size_t i = 0; i < faces.size(); ++i) {
        const Eigen::Vector3d a = mesh.V.row(mesh.F(faces[i], 0));
        const Eigen::Vector3d b = mesh.V.row(mesh.F(faces[i], 1));
        const Eigen::Vector3d c = mesh.V.row(mesh.F(faces[i], 2));
        const Eigen::Vector3d n = (b - a).cross(c - a).normalized();  // zero if degenerate
        const std::array<Eigen::Vector3d, 3> corners{a, b, c};
        for (unsigned k = 0; k < 3; ++k) {
          const auto v = static_cast<unsigned>(3 * i + k);
          out->mVertices[v] = to_ai(corners[k]);
          out->mNormals[v] = to_ai(n.allFinite() ? n : Eigen::Vector3d::Zero());
          out->mFaces[i].mIndices[k] = v;
        }
      }
    } else {
      std::vector<Eigen::Index> vertices;  // this part's vertices, in order of first use
      for (std::size_t i = 0; i < faces.size(); ++i) {
        for (int k = 0; k < 3; ++k) {
          unsigned& slot = local[static_cast<std::size_t>(mesh.F(faces[i], k))];
          if (slot == 0) {
            vertices.push_back(mesh.F(faces[i], k));
            slot = static_cast<unsigned>(vertices.size());
          }
          out->mFaces[i].mIndices[k] = slot - 1;
        }
      }
      out->mNumVertices = static_cast<unsigned>(vertices.size());
      out->mVertices = new aiVector3D[vertices.size()];
      for (std::size_t i = 0; i < vertices.size(); ++i) {
        out->mVertices[i] = to_ai(mesh.V.row(vertices[i]).transpose());
        local[static_cast<std::size_t>(vertices[i])] = 0;
      }
    }

    auto* node = new aiNode(names[used[m]]);
    node->mParent = scene->mRootNode;
    node->mMeshes = new unsigned[1]{m};
    node->mNumMeshes = 1;
    scene->mRootNode->mChildren[m] = node;
  }

  Assimp::Exporter exporter;
  if (exporter.Export(scene.get(), format, file.string()) != aiReturn_SUCCESS) {
    fail(file, std::string("assimp cannot write it: ") + exporter.GetErrorString());
  }
}

double surface_area(const TriangleMesh& mesh) {
  double area = 0.0;
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    const Eigen::Vector3d a = mesh.V.row(mesh.F(f, 0));
    const Eigen::Vector3d b = mesh.V.row(mesh.F(f, 1));
    const Eigen::Vector3d c = mesh.V.row(mesh.F(f, 2));
    area += 0.5 * (b - a).cross(c - a).norm();
  }
  return area;
}

Eigen::AlignedBox3d bounding_box(const TriangleMesh& mesh) {
  Eigen::AlignedBox3d box;  // starts empty
  for (Eigen::Index v = 0; v < mesh.V.rows(); ++v) box.extend(mesh.V.row(v).transpose().eval());
  return box;
}

void check_extent(const TriangleMesh& mesh, const std::string& name, double domain_diagonal,
                  double factor) {
  const Eigen::AlignedBox3d box = bounding_box(mesh);
  if (box.isEmpty() || !(domain_diagonal > 0.0)) return;
  const double diagonal = box.diagonal().norm();
  if (diagonal <= factor * domain_diagonal) return;
  std::ostringstream text;
  text << "mesh '" << name << "': its bounding box (diagonal " << diagonal << ") is "
       << diagonal / domain_diagonal << " times the grid's (" << domain_diagonal
       << "); coordinates in other units? (millimetres for metres: scale 0.001)";
  throw MeshError(text.str());
}

}  // namespace mpmgeom
