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

/// Appends frames to OUT.h5 (group /frames/NNNNNN per frame) and keeps OUT.xmf valid after
/// every frame (rewritten to a temporary file and renamed), so a killed run leaves a readable
/// time series of everything written so far.
class ParticleWriter {
 public:
  /// Creates (truncates) the HDF5 file and the XDMF file. Throws std::runtime_error naming the
  /// file on failure.
  ParticleWriter(const std::filesystem::path& h5_path, const std::filesystem::path& xmf_path);
  /// Reopens the files of an earlier run to continue it: keeps its first `keep_frames` frames,
  /// deletes any later ones (written after the checkpoint being resumed) and rewrites the index.
  ParticleWriter(const std::filesystem::path& h5_path, const std::filesystem::path& xmf_path,
                 std::size_t keep_frames);
  ~ParticleWriter();
  ParticleWriter(const ParticleWriter&) = delete;
  ParticleWriter& operator=(const ParticleWriter&) = delete;

  /// Writes one frame, flushes the HDF5 file, then rewrites the XDMF index.
  void write(const ParticleFrame& frame);
  [[nodiscard]] std::size_t frames_written() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// Reads frame `index` (0-based, in write order) back from an HDF5 file written by
/// ParticleWriter. Throws std::runtime_error naming the file on failure.
ParticleFrame read_frame(const std::filesystem::path& h5_path, std::size_t index);

/// Number of frames stored in an HDF5 file written by ParticleWriter.
std::size_t count_frames(const std::filesystem::path& h5_path);

}  // namespace mpm
