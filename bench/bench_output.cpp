// Time of the particle output (ParticleWriter): N frames of 1,000 particles written one after
// another into the temporary directory, with a pause of G milliseconds between frames standing
// for the steps a run takes between them. Frame files are synced to the disk, so the times are
// the disk's as much as the code's; what the benchmark shows is how the time per frame grows
// with the frames already written (the indexes list every frame).
//
//   build/bin/bench_output                                # all sizes
//   build/bin/bench_output --benchmark_filter=/4000/0     # 4,000 frames back to back
//
// Counters: ms_per_frame (the mean over the N frames, pauses excluded), ms_last_100 (the mean
// of the last 100 frames), index_rewrites (how often both indexes were rewritten).

#include <benchmark/benchmark.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <string>
#include <thread>

#include "mpm/output.hpp"

namespace {

mpm::ParticleFrame frame_of(std::size_t count, double time) {
  mpm::ParticleFrame f;
  f.time = time;
  f.count = count;
  f.position.assign(3 * count, 1.0);
  f.velocity.assign(3 * count, 0.5);
  f.stress.assign(9 * count, -1e3);
  f.mass.assign(count, 2.0);
  f.volume.assign(count, 1e-3);
  f.material.assign(count, 0);
  f.body.assign(count, 0);
  return f;
}

void BM_WriteFrames(benchmark::State& state) {
  using Clock = std::chrono::steady_clock;
  const auto frames = static_cast<std::size_t>(state.range(0));
  const auto pause = std::chrono::milliseconds(state.range(1));
  const std::filesystem::path dir =
      std::filesystem::temp_directory_path() / ("mpm_bench_output_" + std::to_string(::getpid()));
  mpm::ParticleFrame frame = frame_of(1000, 0.0);
  double writing = 0.0, last = 0.0;
  std::size_t rewrites = 0;
  for (auto _ : state) {
    state.PauseTiming();
    std::filesystem::remove_all(dir);
    std::filesystem::create_directories(dir);
    writing = last = 0.0;
    rewrites = 0;
    state.ResumeTiming();
    mpm::ParticleWriter writer(dir / "particles.h5", dir / "particles.xmf");
    for (std::size_t i = 0; i < frames; ++i) {
      if (pause.count() > 0) std::this_thread::sleep_for(pause);
      frame.time = 0.01 * static_cast<double>(i);
      const std::size_t indexed = writer.frames_indexed();
      const auto start = Clock::now();
      writer.write(frame);
      const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
      writing += seconds;
      if (i + 100 >= frames) last += seconds;
      if (writer.frames_indexed() != indexed) ++rewrites;
    }
    const auto start = Clock::now();
    writer.flush();
    writing += std::chrono::duration<double>(Clock::now() - start).count();
  }
  std::filesystem::remove_all(dir);
  state.counters["ms_per_frame"] = 1e3 * writing / static_cast<double>(frames);
  state.counters["ms_last_100"] =
      1e3 * last / static_cast<double>(std::min<std::size_t>(frames, 100));
  state.counters["index_rewrites"] = static_cast<double>(rewrites);
}
BENCHMARK(BM_WriteFrames)
    ->Args({250, 0})
    ->Args({1000, 0})
    ->Args({4000, 0})
    ->Args({4000, 2})
    ->Iterations(1)
    ->Unit(benchmark::kSecond)
    ->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
