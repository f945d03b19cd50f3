// `mpm verify`: the verification suite of DESIGN.md section 5. Each case has a parameter file in
// data/verification/<case>.json (what to run: angles, friction, resolutions, tolerance, which
// wall methods apply) and a checker (tools/cases.cpp) that builds the scene for one wall method
// and resolution, runs it, and measures the error against the exact answer.

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "cases.hpp"
#include "commands.hpp"

namespace mpm::tools {

using nlohmann::json;

int verify_command(const VerifyArgs& args) {
  std::vector<Check> checks;
  merge_multipliers(args.multiplier_radius);
  use_update_scheme(args.update);
  if (!args.scene_dir.empty()) {
    std::error_code ec;
    std::filesystem::create_directories(args.scene_dir, ec);
    if (ec || !std::filesystem::is_directory(args.scene_dir)) {
      std::cerr << "mpm verify: --scenes " << args.scene_dir.string()
                << ": not a writable folder\n";
      return 2;
    }
  }
  std::vector<std::string> cases = args.cases;
  if (cases.empty()) {
    for (const auto& [name, fn] : checkers()) cases.push_back(name);
  }
  for (const std::string& name : cases) {
    if (checkers().count(name) == 0) {
      std::cerr << "mpm verify: no case \"" << name << "\" (cases:";
      for (const auto& [n, fn] : checkers()) std::cerr << ' ' << n;
      std::cerr << ")\n";
      return 2;
    }
    const std::filesystem::path file = args.data_dir / (name + ".json");
    json p;
    try {
      std::ifstream in(file);
      if (!in) throw std::runtime_error("cannot be read");
      p = json::parse(in);
    } catch (const std::exception& e) {
      std::cerr << "mpm verify: " << file.string() << ": " << e.what() << "\n";
      return 2;
    }
    std::vector<std::string> methods = p.value("methods", std::vector<std::string>{"grid"});
    if (!args.methods.empty()) {
      std::vector<std::string> keep;
      for (const auto& m : methods) {
        if (std::find(args.methods.begin(), args.methods.end(), m) != args.methods.end()) {
          keep.push_back(m);
        }
      }
      methods = keep;
    }
    // --resolution K: that one; --convergence: every one the case lists; else the first.
    std::vector<int> listed = p.value("resolutions", std::vector<int>{1});
    if (listed.empty()) listed.push_back(1);
    std::vector<int> resolutions;
    if (args.resolution > 0) {
      resolutions.push_back(args.resolution);
    } else if (args.convergence) {
      resolutions = listed;
    } else {
      resolutions.push_back(listed.front());
    }
    for (const std::string& method : methods) {
      for (const int k : resolutions) {
        std::vector<Check> got;
        if (!args.scene_dir.empty()) {
          dump_scenes(args.scene_dir, name + "_" + method + "_k" + std::to_string(k));
        }
        try {
          got = checkers().at(name)(p.at("params"), method, k);
        } catch (const NotApplicable& e) {
          std::printf("%-22s %-9s %2d  not run: %s\n", name.c_str(), method.c_str(), k, e.what());
          std::fflush(stdout);
          continue;
        } catch (const std::exception& e) {
          std::cerr << "mpm verify: " << file.string() << ": " << e.what() << "\n";
          return 2;
        }
        for (Check& c : got) {
          c.pass = c.note.empty() && std::isfinite(c.value) && c.value <= c.tolerance;
          std::printf("%-22s %-9s %2d  %-44s %10.3e %9.2e  %-4s %7.2f s%s%s\n", c.case_name.c_str(),
                      c.method.c_str(), c.resolution, c.measure.c_str(), c.value, c.tolerance,
                      c.pass ? "pass" : "FAIL", c.seconds, c.note.empty() ? "" : "  ",
                      c.note.c_str());
          std::fflush(stdout);
          checks.push_back(c);
        }
      }
    }
  }
  bool all = true;
  json out = json::array();
  for (const Check& c : checks) {
    all = all && c.pass;
    out.push_back({{"case", c.case_name},
                   {"method", c.method},
                   {"resolution", c.resolution},
                   {"measure", c.measure},
                   {"value", c.value},
                   {"tolerance", c.tolerance},
                   {"pass", c.pass},
                   {"seconds", c.seconds},
                   {"note", c.note}});
  }
  if (!args.json_file.empty()) {
    std::ofstream f(args.json_file);
    f << out.dump(1) << "\n";
    if (!f) {
      std::cerr << "mpm verify: cannot write " << args.json_file.string() << "\n";
      return 4;
    }
  }
  std::size_t passed = 0;
  for (const Check& c : checks) passed += c.pass ? 1 : 0;
  std::printf("%zu of %zu checks pass\n", passed, checks.size());
  return all ? 0 : 1;
}

}  // namespace mpm::tools
