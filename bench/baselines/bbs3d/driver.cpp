// A line-protocol driver around the public 3D-BBS CPU library (Aoki et al., ICRA 2024), for
// blockloc's benchmarks only. blockloc never links it; bench/_bbs3d.py builds this file against a
// checkout of https://github.com/KOKIAOKI/3d_bbs and talks to it over stdin/stdout.
//
// stdin, one command a line (points files: raw little-endian float64, N x 3, row-major):
//   map PATH MIN_LEVEL_RES MAX_LEVEL NUM_THREADS
//       builds the hierarchical voxel maps; answers {"prep_ms": ...}
//   loc PATH MINX MINY MINZ MAXX MAXY MAXZ MINROLL MINPITCH MINYAW MAXROLL MAXPITCH MAXYAW SCORE_PCT TIMEOUT_MS
//       localizes one gravity-aligned scan (sensor frame) inside the translation box and angle
//       ranges (m, rad); answers {"localized":..,"timed_out":..,"score":..,"score_pct":..,
//       "ms":..,"T":[16 numbers, row-major T_map_scan]}
//   quit
#include <cpu_bbs3d/bbs3d.hpp>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

static std::vector<Eigen::Vector3d> read_points(const std::string& path) {
  std::ifstream in(path, std::ios::binary | std::ios::ate);
  std::vector<Eigen::Vector3d> pts;
  if (!in) return pts;
  const std::streamsize bytes = in.tellg();
  in.seekg(0);
  std::vector<double> buf(static_cast<size_t>(bytes) / sizeof(double));
  in.read(reinterpret_cast<char*>(buf.data()), static_cast<std::streamsize>(buf.size() * sizeof(double)));
  pts.reserve(buf.size() / 3);
  for (size_t i = 0; i + 2 < buf.size(); i += 3) pts.emplace_back(buf[i], buf[i + 1], buf[i + 2]);
  return pts;
}

int main() {
  std::ios::sync_with_stdio(false);
  cpu::BBS3D bbs;
  bool have_map = false;
  std::string line;
  while (std::getline(std::cin, line)) {
    std::istringstream ss(line);
    std::string cmd;
    ss >> cmd;
    if (cmd == "quit") break;
    if (cmd == "map") {
      std::string path;
      double res;
      int levels, threads;
      ss >> path >> res >> levels >> threads;
      const auto pts = read_points(path);
      if (pts.empty()) {
        std::cout << "{\"error\": \"no points in " << path << "\"}" << std::endl;
        continue;
      }
      const auto t0 = std::chrono::steady_clock::now();
      bbs.set_tar_points(pts, res, levels);
      bbs.set_num_threads(threads);
      const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
      have_map = true;
      std::cout << "{\"prep_ms\": " << ms << ", \"points\": " << pts.size() << "}" << std::endl;
    } else if (cmd == "loc") {
      std::string path;
      Eigen::Vector3d lo, hi, rlo, rhi;
      double pct;
      int timeout_ms;
      ss >> path >> lo.x() >> lo.y() >> lo.z() >> hi.x() >> hi.y() >> hi.z() >> rlo.x() >> rlo.y() >> rlo.z() >> rhi.x() >>
        rhi.y() >> rhi.z() >> pct >> timeout_ms;
      const auto pts = read_points(path);
      if (!have_map || pts.empty()) {
        std::cout << "{\"error\": \"" << (have_map ? "no points in " + path : std::string("no map")) << "\"}" << std::endl;
        continue;
      }
      bbs.set_src_points(pts);
      bbs.set_trans_search_range(lo, hi);
      bbs.set_angular_search_range(rlo, rhi);
      bbs.set_score_threshold_percentage(pct);
      if (timeout_ms > 0) {
        bbs.enable_timeout();
        bbs.set_timeout_duration_in_msec(timeout_ms);
      } else {
        bbs.disable_timeout();
      }
      bbs.localize();
      const Eigen::Matrix4d T = bbs.get_global_pose();
      std::ostringstream out;
      out.precision(17);
      out << "{\"localized\": " << (bbs.has_localized() ? "true" : "false") << ", \"timed_out\": "
          << (bbs.has_timed_out() ? "true" : "false") << ", \"score\": " << bbs.get_best_score()
          << ", \"score_pct\": " << bbs.get_best_score_percentage() << ", \"ms\": " << bbs.get_elapsed_time() << ", \"T\": [";
      for (int r = 0; r < 4; ++r)
        for (int c = 0; c < 4; ++c) out << T(r, c) << ((r == 3 && c == 3) ? "" : ", ");
      out << "]}";
      std::cout << out.str() << std::endl;
    } else if (!cmd.empty()) {
      std::cout << "{\"error\": \"unknown command " << cmd << "\"}" << std::endl;
    }
  }
  return 0;
}
