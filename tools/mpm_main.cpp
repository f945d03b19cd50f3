// `mpm`: one command, one subcommand per job. Parse, call the library, report.

#include <iostream>

#include <tbb/global_control.h>
#include <CLI/CLI.hpp>

#include "mpm/run.hpp"
#include "mpm/scene.hpp"

int main(int argc, char** argv) {
  CLI::App app{"Material Point Method with dual-grid bounding surfaces", "mpm"};
  app.set_version_flag("--version", std::string("mpm ") + MPM_VERSION);
  app.require_subcommand(1);

  std::string scene_file;
  mpm::RunOptions run_options;
  int threads = 0;
  CLI::App* run = app.add_subcommand("run", "Run a scene (JSON) and write results to OUTDIR");
  run->add_option("scene", scene_file, "Scene file (JSON)")->required();
  run->add_option("-o,--output", run_options.out_dir, "Output directory")->required();
  run->add_flag("--overwrite", run_options.overwrite, "Replace an earlier result in OUTDIR");
  run->add_flag("-q,--quiet", run_options.quiet, "No progress display");
  run->add_option("-j,--threads", threads, "Worker threads (default: all cores)")
      ->check(CLI::Range(1, 1024));

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : mpm::kExitBadInput;
  }

  std::unique_ptr<tbb::global_control> thread_limit;
  if (threads > 0) {
    thread_limit = std::make_unique<tbb::global_control>(
        tbb::global_control::max_allowed_parallelism, static_cast<std::size_t>(threads));
  }

  if (*run) {
    try {
      const mpm::Scene scene = mpm::load_scene(scene_file);
      return mpm::run_scene(scene, run_options);
    } catch (const mpm::SceneError& e) {
      std::cerr << "mpm: " << e.what() << '\n';
      return mpm::kExitBadInput;
    }
  }
  return 0;
}
