// libFuzzer target: mesh import (assimp) and validation/repair (CGAL), the path every wall,
// terrain and source-volume mesh takes. The first byte picks the format the rest is read as.
// Any input must give a mesh or a MeshError; any other exception, a crash or a sanitizer report
// is a finding.

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include "fuzz_file.hpp"
#include "mpmgeom/mesh_repair.hpp"
#include "mpmgeom/triangle_mesh.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1) return 0;
  static const char* const kExtensions[] = {".obj", ".stl", ".ply", ".off"};
  const std::filesystem::path file = fuzz_file("mpm_fuzz_mesh", kExtensions[data[0] % 4]);
  {
    std::ofstream out(file, std::ios::binary | std::ios::trunc);
    out.write(reinterpret_cast<const char*>(data + 1), static_cast<std::streamsize>(size - 1));
  }
  try {
    // In this process, so that the fuzzer sees assimp's coverage. MPM_FUZZ_ISOLATE=1 takes the
    // production path instead, load_mesh's child process (which turns the reader's aborts, hangs
    // and runaway allocations into a MeshError): run_fuzzer.sh reruns out-of-memory inputs so.
    static const bool isolate = std::getenv("MPM_FUZZ_ISOLATE") != nullptr;
    mpmgeom::ImportOptions import;
    import.isolate = isolate;
    const mpmgeom::TriangleMesh mesh = mpmgeom::load_mesh(file, import);
    mpmgeom::RepairOptions options;
    options.require_closed = (data[0] & 4) != 0;  // as a source volume
    (void)mpmgeom::validate_and_repair(mesh, file.string(), options);
  } catch (const mpmgeom::MeshError&) {
    // Rejected with a message naming the file.
  }
  std::filesystem::remove(file);
  return 0;
}
