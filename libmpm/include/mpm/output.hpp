#pragma once
// Particle output: HDF5 snapshots plus an XDMF index that ParaView opens as a time series.
// Plain arrays only; HDF5 stays inside output.cpp.

#include <cstdint>
#include <filesystem>
#include <memory>
#include <vector>

namespace mpm {

/// One snapshot of the particle state. Vectors are padded to 3 components and tensors to a full
/// row-major 3x3 block whatever the dimension, because XDMF geometry and tensors are 3D.
struct ParticleFrame {
  double time = 0.0;
  std::int64_t step = 0;
  std::size_t count = 0;
  std::vector<double> position;  ///< count x 3
  std::vector<double> velocity;  ///< count x 3
  std::vector<double> stress;    ///< count x 9, Cauchy stress, row-major
  std::vector<double> mass;      ///< count
  std::vector<double> volume;    ///< count (current volume)
  std::vector<int> material;     ///< count, index into the scene's materials
  std::vector<int> body;         ///< count, index into the scene's bodies
};

/// Writes each frame to its own file, OUT/NNNNNN.h5 (beside OUT.h5, in a directory named after
/// it), and keeps two indexes of them: OUT.h5, whose /frames/NNNNNN are external links to the
/// frame files (so h5py or read_frame() open it like one file), and OUT.xmf for ParaView. No file
/// is changed once written: each is written to a temporary file and renamed, so a run killed at
/// any moment leaves every frame before it intact and readable, and OUT.h5 and OUT.xmf as they
/// were after their last rewrite. (HDF5 changes a file in place, and a process killed while it
/// did could leave the links of a single growing file pointing at garbage.) The indexes list every
/// frame, so they are rewritten after each frame only while that is cheap: for the first 256
/// frames, then whenever the time spent rewriting them since stays within 2% of the wall clock
/// since (a run of thousands of frames would otherwise spend most of its output time on them),
/// and by flush(). A killed run's indexes may lack its last few frames; a resume rebuilds them.
class ParticleWriter {
 public:
  /// Creates (truncates) the indexes and the frame directory (its parent must exist), removing
  /// an earlier run's frame files. Throws std::runtime_error naming the file on failure.
  ParticleWriter(const std::filesystem::path& h5_path, const std::filesystem::path& xmf_path);
  /// Continues an earlier run: keeps its first `keep_frames` frame files (throws naming the first
  /// one missing or unreadable), deletes later and unfinished ones (written after the checkpoint
  /// being resumed) and rewrites both indexes from the frame files, whatever state a kill left
  /// them in.
  ParticleWriter(const std::filesystem::path& h5_path, const std::filesystem::path& xmf_path,
                 std::size_t keep_frames);
  ~ParticleWriter();
  ParticleWriter(const ParticleWriter&) = delete;
  ParticleWriter& operator=(const ParticleWriter&) = delete;

  /// Writes one frame file (synced to the disk before it takes its name), then both indexes if
  /// they are due (above).
  void write(const ParticleFrame& frame);
  /// Rewrites both indexes if they lack a frame written. Throws std::runtime_error naming the
  /// file on failure. The destructor flushes too, but cannot report a failure.
  void flush();
  [[nodiscard]] std::size_t frames_written() const;
  /// The frames the indexes on the disk list (frames_written() after flush()).
  [[nodiscard]] std::size_t frames_indexed() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// The directory of ParticleWriter's frame files: OUT.h5's name without the extension, beside it.
std::filesystem::path frame_directory(const std::filesystem::path& h5_path);

/// Reads frame `index` (0-based, in write order) back from an HDF5 file written by
/// ParticleWriter. Throws std::runtime_error naming the file on failure.
ParticleFrame read_frame(const std::filesystem::path& h5_path, std::size_t index);

/// Number of frames stored in an HDF5 file written by ParticleWriter.
std::size_t count_frames(const std::filesystem::path& h5_path);

}  // namespace mpm
