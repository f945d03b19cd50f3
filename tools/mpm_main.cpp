// `mpm`: one command, one subcommand per job. Parse, call the library, report.

#include <iostream>
#include <string>
#include <utility>

#ifdef __GLIBC__
#include <malloc.h>
#endif

#include <tbb/global_control.h>
#include <CLI/CLI.hpp>

#include "commands.hpp"
#include "mpm/run.hpp"
#include "mpm/scene.hpp"

int main(int argc, char** argv) {
#ifdef __GLIBC__
  // Freed memory stays in the heap for the next allocation. The couplings allocate and free
  // blocks of megabytes at each factorisation (Eigen's permuted copy of the matrix; Enhanced's
  // K, W and contact system, formed to be factorised): glibc returned them to the kernel and
  // took the page faults to map them again, 238,578 of them in 300 steps of the Enhanced
  // floor benchmark, 82,180 with this (61.8 -> 50.5 ms a step; docs/performance.md,
  // 2026-12-07, night). Blocks of 32 MiB or more are still mapped apart.
  mallopt(M_MMAP_THRESHOLD, 32 << 20);
  mallopt(M_TRIM_THRESHOLD, 1 << 30);
#endif
  CLI::App app{"Material Point Method with dual-grid bounding surfaces", "mpm"};
  app.set_version_flag("--version", std::string("mpm ") + MPM_VERSION);
  app.require_subcommand(1);
  // Errors on the command line in one line, as every other error of the command (CLI11's
  // default adds a second line pointing to --help).
  app.failure_message([](const CLI::App* /*app*/, const CLI::Error& e) {
    return std::string("mpm: ") + e.what() + " (--help lists the options)\n";
  });

  std::string scene_file;
  mpm::RunOptions run_options;
  int threads = 0;
  // -j: every subcommand that runs scenes takes it.
  const auto add_threads = [&threads](CLI::App* sub) {
    sub->add_option("-j,--threads", threads, "Worker threads (default: all cores)")
        ->check(CLI::Range(1, 1024));
  };
  CLI::App* run = app.add_subcommand("run", "Run a scene (JSON) and write results to OUTDIR");
  std::filesystem::path resume_dir;
  auto* scene_option = run->add_option("scene", scene_file, "Scene file (JSON)");
  auto* out_option = run->add_option("-o,--output", run_options.out_dir, "Output directory");
  auto* resume_option = run->add_option(
      "--resume", resume_dir, "Continue the unfinished run in OUTDIR from its last checkpoint");
  resume_option->excludes(scene_option)->excludes(out_option);
  scene_option->needs(out_option);
  out_option->needs(scene_option);
  run->add_flag("--overwrite", run_options.overwrite, "Replace an earlier result in OUTDIR")
      ->excludes(resume_option);
  run->add_flag("-q,--quiet", run_options.quiet, "No progress display");
  int resolution = 1;
  run->add_option("--resolution", resolution,
                  "Refine the scene K times: grid spacing / K, particles per cell kept (K^D times "
                  "the particles); a resumed run keeps its own")
      ->check(CLI::Range(1, 16))
      ->excludes(resume_option);
  add_threads(run);

  mpm::tools::PrepArgs prep_args;
  CLI::App* prep = app.add_subcommand(
      "prep", "Turn a wall or terrain surface mesh into a boundary package (layer + coupling)");
  prep->add_option("mesh", prep_args.mesh, "Surface mesh (any format assimp reads)")->required();
  prep->add_option("-o,--output", prep_args.output, "Boundary package OUT.h5 (+ OUT.xmf)")
      ->required();
  prep->add_option("--spacing", prep_args.spacing, "Standard grid spacing h")
      ->required()
      ->check(CLI::PositiveNumber);
  prep->add_option("--thickness", prep_args.options.layer.thickness,
                   "Layer thickness t (default h)")
      ->check(CLI::PositiveNumber);
  prep->add_option("--layers", prep_args.options.layer.layers, "Sub-layers")
      ->check(CLI::Range(1, 16));
  prep->add_option("--origin", prep_args.origin, "Grid box minimum X,Y,Z (default: fits the mesh)")
      ->delimiter(',')
      ->expected(3);
  prep->add_option("--box-max", prep_args.box_max, "Grid box maximum X,Y,Z (with --origin)")
      ->delimiter(',')
      ->expected(3);
  prep->add_option("--shape", prep_args.shape, "Shape function of the standard grid")
      ->check(CLI::IsMember({"linear", "gimp", "bspline2"}));
  prep->add_option("--scale", prep_args.options.import.scale, "Scale the mesh (units)")
      ->check(CLI::PositiveNumber);
  std::vector<double> translate, rotate;
  prep->add_option("--translate", translate, "Translate the mesh X,Y,Z")
      ->delimiter(',')
      ->expected(3);
  prep->add_option("--rotate", rotate, "Rotate the mesh about x, y, z (degrees)")
      ->delimiter(',')
      ->expected(3);
  bool no_remesh = false;
  prep->add_flag("--no-remesh", no_remesh, "Keep the mesh as it is (no isotropic remeshing)");
  prep->add_flag("--closed", prep_args.options.repair.require_closed,
                 "The surface must be closed (a structure or source volume)");
  prep->add_flag("--overwrite", prep_args.overwrite, "Replace an existing package");

  mpm::tools::VerifyArgs verify_args;
  verify_args.data_dir = MPM_VERIFICATION_DIR;
  CLI::App* verify = app.add_subcommand(
      "verify", "Run the verification cases against their exact answers and print the table");
  verify->add_option("--case", verify_args.cases, "Case name (repeatable; default: all)");
  verify->add_option("--method", verify_args.methods,
                     "Wall method: grid, sdf, one-way, mortar, enhanced (repeatable)");
  verify
      ->add_option("--resolution", verify_args.resolution,
                   "Refinement factor K (spacing h/K; default: the case's first)")
      ->check(CLI::Range(1, 64));
  verify->add_flag("--convergence", verify_args.convergence,
                   "Every resolution the case lists (for the observed order)");
  verify->add_option("--json", verify_args.json_file, "Write the table as JSON");
  verify->add_option("--scenes", verify_args.scene_dir,
                     "Write every scene run to DIR as JSON (rerun one with mpm run)");
  verify
      ->add_option("--multiplier-radius", verify_args.multiplier_radius,
                   "Blending walls merge Phi's multipliers within this many cell spacings "
                   "(the scene key multiplier_radius; default 0: one per Phi node)")
      ->check(CLI::Range(0.0, 8.0));
  verify
      ->add_option("--update", verify_args.update,
                   "Update scheme of every case: musl, usl or mls (default: the cases' own, "
                   "musl); mls skips the cases on another kernel than bspline2")
      ->check(CLI::IsMember({"musl", "usl", "mls"}));
  verify->add_option("--data", verify_args.data_dir, "Folder of the case files")
      ->check(CLI::ExistingDirectory);
  add_threads(verify);

  mpm::tools::BenchArgs bench_args;
  bench_args.scripts_dir = MPM_SCRIPTS_DIR;
  bench_args.failures = "bench_failures";
  mpm::tools::PerfArgs perf_args;
  CLI::App* bench = app.add_subcommand(
      "bench",
      "Benchmarks: run time against error (accuracy), numerical stress (stability), the step's "
      "speed targets (perf)");
  bench->add_option("kind", bench_args.kind, "accuracy, stability or perf")
      ->required()
      ->check(CLI::IsMember({"accuracy", "stability", "perf"}));
  bench->add_option("--case,--cases", bench_args.cases,
                    "accuracy: series; stability: part (throws, long, cfl, crossing); repeatable");
  bench->add_option("--method,--methods", bench_args.methods,
                    "Wall method: grid, sdf, one-way, mortar, enhanced (repeatable)");
  bench->add_flag("--smoke", bench_args.smoke, "The few configurations the test suite runs");
  bench
      ->add_option("--config", bench_args.config,
                   "Configuration (default data/bench/accuracy.json or stability.json)")
      ->check(CLI::ExistingFile);
  bench->add_option("--csv", bench_args.csv_file, "Write every run as a CSV row");
  bench->add_option("--plot", bench_args.plot_file, "Draw the PNG (python3-matplotlib)");
  bench->add_option("--failures", bench_args.failures,
                    "stability: folder for the scenes of failing runs (default bench_failures)");
  bench->add_option("--seed", bench_args.seed, "stability: random seed of the wall placements");
  bench->add_option("--runs", bench_args.runs, "stability: number of random wall placements")
      ->check(CLI::Range(1, 100000));
  bench->add_option("--cells", perf_args.cells, "perf: the block's cells per side (default 32)")
      ->check(CLI::Range(4, 64));
  bench->add_option("--steps", perf_args.steps, "perf: timed steps per round (default 20)")
      ->check(CLI::Range(1, 10000));
  bench
      ->add_option("--settle", perf_args.settle,
                   "perf: steps each scene takes before its timed rounds (default 5; the "
                   "scaling runs take 1)")
      ->check(CLI::Range(1, 100000));
  bench
      ->add_option("--rounds", perf_args.rounds,
                   "perf: rounds per scene, interleaved with the other scenes' (default 5, 1 with "
                   "--smoke; the median is reported)")
      ->check(CLI::Range(1, 100));
  CLI::Option* yardstick =
      bench
          ->add_option("--yardstick", perf_args.yardstick,
                       "perf: the yardstick's M particle-steps/s on all threads, measured in the "
                       "same session (../shared/tools/yardstick/run.sh)")
          ->check(CLI::Range(1e-3, 1e3));
  bench
      ->add_option("--yardstick-script", perf_args.yardstick_script,
                   "perf: run the yardstick's script (../shared/tools/yardstick/run.sh) once per "
                   "round of the standard block, interleaved with them, for the throughput ratio")
      ->excludes(yardstick);
  bench->add_option("--json", perf_args.json_file, "perf: write the timings as JSON");
  add_threads(bench);

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

  if (*prep) {
    if (!translate.empty())
      prep_args.options.import.translation = {translate[0], translate[1], translate[2]};
    if (!rotate.empty()) prep_args.options.import.rotation_deg = {rotate[0], rotate[1], rotate[2]};
    prep_args.options.remesh = !no_remesh;
    return mpm::tools::prep_command(prep_args);
  }
  if (*verify) return mpm::tools::verify_command(verify_args);
  if (*bench) {
    // Each kind's own options: one given to another kind is refused, not ignored.
    const std::pair<const char*, const char*> kinds_of[] = {{"--case", "accuracy and stability"},
                                                            {"--method", "accuracy and stability"},
                                                            {"--config", "accuracy and stability"},
                                                            {"--csv", "accuracy and stability"},
                                                            {"--plot", "accuracy and stability"},
                                                            {"--failures", "stability"},
                                                            {"--seed", "stability"},
                                                            {"--runs", "stability"},
                                                            {"--cells", "perf"},
                                                            {"--steps", "perf"},
                                                            {"--rounds", "perf"},
                                                            {"--settle", "perf"},
                                                            {"--yardstick", "perf"},
                                                            {"--yardstick-script", "perf"},
                                                            {"--json", "perf"}};
    for (const auto& [option, kinds] : kinds_of) {
      const std::string allowed = std::string(" ") + kinds + " ";
      if (bench->count(option) > 0 &&
          allowed.find(" " + bench_args.kind + " ") == std::string::npos) {
        std::cerr << "mpm bench " << bench_args.kind << ": " << option << " is not an option of "
                  << bench_args.kind << " (only of " << kinds << ")\n";
        return mpm::kExitBadInput;
      }
    }
    if (bench_args.kind == "perf") {
      perf_args.smoke = bench_args.smoke;
      return mpm::tools::perf_command(perf_args);
    }
    if (bench_args.config.empty()) {
      bench_args.config = std::filesystem::path(MPM_BENCH_DIR) / (bench_args.kind + ".json");
    }
    return mpm::tools::bench_command(bench_args);
  }
  if (*run) {
    try {
      if (!resume_dir.empty()) {
        run_options.out_dir = resume_dir;
        run_options.resume = true;
        const mpm::CheckpointOrigin origin = mpm::checkpoint_origin(resume_dir);
        scene_file = origin.scene.string();
        resolution = origin.resolution;
      } else if (scene_file.empty()) {
        std::cerr << "mpm run: give a scene and -o OUTDIR, or --resume OUTDIR\n";
        return mpm::kExitBadInput;
      }
      const mpm::Scene scene = mpm::load_scene(scene_file, resolution);
      return mpm::run_scene(scene, run_options);
    } catch (const std::runtime_error& e) {  // a SceneError, or no readable checkpoint
      std::cerr << "mpm: " << e.what() << '\n';
      return mpm::kExitBadInput;
    }
  }
  return 0;
}
