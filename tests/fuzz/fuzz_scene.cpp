// libFuzzer target: the scene loader. Any input must give a Scene or a SceneError (the one-line
// message `mpm run` prints); any other exception, a crash or a sanitizer report is a finding.
// Run: build-fuzz/tests/fuzz_scene CORPUS_DIR data/scenes -max_total_time=600 (docs/reliability.md)

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>

#include "fuzz_file.hpp"
#include "mpm/scene.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  // The loader reads files (and resolves mesh paths next to them): write the input as one.
  static const std::filesystem::path file = fuzz_file("mpm_fuzz_scene", ".json");
  {
    std::ofstream out(file, std::ios::binary | std::ios::trunc);
    out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
  }
  try {
    const mpm::Scene scene = mpm::load_scene(file);
    (void)scene;
  } catch (const mpm::SceneError&) {
    // Rejected with a message: what bad input must get.
  }
  return 0;
}
