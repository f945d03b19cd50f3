// `mpm prep MESH --spacing H -o OUT.h5`: surface mesh -> boundary package.

#include <chrono>
#include <cmath>
#include <cstdio>
#include <iostream>

#include "commands.hpp"
#include "mpm/run.hpp"
#include "mpmgeom/triangle_mesh.hpp"

namespace mpm::tools {

int prep_command(const PrepArgs& args) {
  namespace fs = std::filesystem;
  const auto start = std::chrono::steady_clock::now();
  const double h = args.spacing;
  fs::path xmf = args.output;
  xmf.replace_extension(".xmf");
  std::error_code ec;
  if (fs::exists(args.output, ec) && !args.overwrite) {
    std::cerr << "mpm prep: " << args.output.string()
              << ": exists; choose another name or pass --overwrite\n";
    return kExitBadInput;
  }
  const ShapeKind shape = args.shape == "linear" ? ShapeKind::linear
                          : args.shape == "gimp" ? ShapeKind::gimp
                                                 : ShapeKind::bspline2;
  try {
    PrepOptions options = args.options;
    if (options.layer.thickness <= 0.0) options.layer.thickness = h;  // default t = h
    std::string why;
    if (!options.import.valid(&why) || !options.layer.valid(&why)) {
      std::cerr << "mpm prep: " << why << '\n';
      return kExitBadInput;
    }
    // The grid box: given, or the mesh box grown by the layer and two cells, on the h lattice.
    const mpmgeom::TriangleMesh mesh = mpmgeom::load_mesh(args.mesh, options.import);
    Eigen::VectorXd box_min(3), box_max(3);
    if (args.origin.empty() || args.box_max.empty()) {
      const Eigen::AlignedBox3d bounds = mpmgeom::bounding_box(mesh);
      const double margin = options.layer.thickness + 2.0 * h;
      for (int d = 0; d < 3; ++d) {
        const double lo = args.origin.empty() ? bounds.min()[d] - margin : args.origin[d];
        box_min[d] = lo;
        const double cells = std::ceil((bounds.max()[d] + margin - lo) / h);
        box_max[d] = args.box_max.empty() ? lo + cells * h : args.box_max[d];
      }
    } else {
      for (int d = 0; d < 3; ++d) {
        box_min[d] = args.origin[d];
        box_max[d] = args.box_max[d];
      }
    }
    for (int d = 0; d < 3; ++d) {
      const double cells = (box_max[d] - box_min[d]) / h;
      if (!(cells >= 1.0) || std::abs(cells - std::round(cells)) > 1e-6 * cells) {
        std::cerr << "mpm prep: --box-max: the box extent on axis " << d
                  << " must be a positive whole number of cells of --spacing " << h << '\n';
        return kExitBadInput;
      }
    }
    const mpmgeom::GridSpec grid = standard_grid_spec(3, box_min, box_max, h, shape);
    const BoundaryPackage package = prepare_boundary(mesh, args.mesh, options, grid);
    if (!args.output.parent_path().empty()) fs::create_directories(args.output.parent_path());
    save_boundary_package(package, args.output, xmf);

    const auto& r = package.report;
    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    std::printf("boundary package %s (+ %s)\n", args.output.c_str(), xmf.filename().c_str());
    std::printf("  grid box     [%g %g %g] to [%g %g %g], h = %g, kernel %s\n", box_min[0],
                box_min[1], box_min[2], box_max[0], box_max[1], box_max[2], h, args.shape.c_str());
    std::printf("  layer        %zu cells, %zu nodes, %d sub-layer(s), t = %g\n", r.cells, r.nodes,
                options.layer.layers, options.layer.thickness);
    std::printf("  parts        %zu\n", package.layer.part_names.size());
    for (const auto& line : package.repairs.repairs)
      std::printf("  repaired     %s\n", line.c_str());
    std::printf("  jacobian     min %.4g (relative to the nominal cell)\n", r.min_jacobian);
    std::printf("  shrunk       %zu columns, by at most %.1f%%\n", r.columns_shrunk,
                100.0 * r.max_shrink);
    std::printf("  creases      %zu vertex normals set to the bisector of a crease\n",
                r.crease_normals);
    std::printf("  Gamma area   %.6g\n  Phi area     %.6g\n  layer volume %.6g\n", r.wall_measure,
                r.interface_measure, r.volume);
    std::printf("  multipliers  %zu on Phi, %zu on Gamma\n",
                package.interface_coupling.multiplier_node.size(),
                package.wall_coupling.multiplier_node.size());
    std::printf("  time         %.2f s\n", seconds);
    return kExitOk;
  } catch (const mpmgeom::MeshError& e) {
    std::cerr << "mpm prep: " << e.what() << '\n';
    return kExitBadInput;
  } catch (const std::invalid_argument& e) {
    std::cerr << "mpm prep: " << e.what() << '\n';
    return kExitBadInput;
  } catch (const std::exception& e) {
    std::cerr << "mpm prep: " << e.what() << '\n';
    return kExitIo;
  }
}

}  // namespace mpm::tools
