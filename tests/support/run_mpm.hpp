#pragma once
// Runs the built `mpm` as a user would, for end-to-end tests.

#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

namespace mpm::test {

namespace fs = std::filesystem;

struct RunResult {
  int exit_code = -1;  ///< the process exit status, or 128 + signal if it was killed
  std::string out;     ///< stdout
  std::string err;     ///< stderr
};

inline std::string slurp(std::FILE* f) {
  std::string text;
  std::rewind(f);
  char buffer[4096];
  std::size_t n = 0;
  while ((n = std::fread(buffer, 1, sizeof buffer, f)) > 0) text.append(buffer, n);
  return text;
}

/// Starts the built `mpm` with `args` (no shell, so paths need no quoting), stdin from /dev/null
/// and stdout/stderr to the given descriptors (-1: inherited). Returns the child's pid, or -1.
inline pid_t start_mpm(const std::vector<std::string>& args, int out_fd = -1, int err_fd = -1) {
  std::vector<std::string> argv_text{MPM_BINARY};
  argv_text.insert(argv_text.end(), args.begin(), args.end());
  std::vector<char*> argv;
  for (auto& a : argv_text) argv.push_back(a.data());
  argv.push_back(nullptr);

  std::fflush(nullptr);
  const pid_t pid = ::fork();
  if (pid == 0) {
    const int devnull = ::open("/dev/null", O_RDONLY);
    if (devnull >= 0) ::dup2(devnull, STDIN_FILENO);
    if (out_fd >= 0) ::dup2(out_fd, STDOUT_FILENO);
    if (err_fd >= 0) ::dup2(err_fd, STDERR_FILENO);
    ::execv(argv[0], argv.data());
    ::_exit(127);  // exec failed; only async-signal-safe calls here
  }
  return pid;
}

/// Runs the built `mpm` with `args`. stdout and stderr go to anonymous temporary files rather
/// than pipes so a chatty child can never block on a full pipe.
inline RunResult run_mpm(const std::vector<std::string>& args) {
  RunResult result;
  std::FILE* out = std::tmpfile();
  std::FILE* err = std::tmpfile();
  if (out == nullptr || err == nullptr) {
    ADD_FAILURE() << "tmpfile() failed";
    if (out != nullptr) std::fclose(out);
    if (err != nullptr) std::fclose(err);
    return result;
  }
  const pid_t pid = start_mpm(args, ::fileno(out), ::fileno(err));
  if (pid < 0) {
    ADD_FAILURE() << "fork() failed";
  } else {
    int status = 0;
    while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
    }
    if (WIFEXITED(status)) {
      result.exit_code = WEXITSTATUS(status);
    } else if (WIFSIGNALED(status)) {
      result.exit_code = 128 + WTERMSIG(status);
    }
  }
  result.out = slurp(out);
  result.err = slurp(err);
  std::fclose(out);
  std::fclose(err);
  return result;
}

inline std::string read_text(const fs::path& file) {
  std::ifstream in(file, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

inline void write_text(const fs::path& file, const std::string& text) {
  std::ofstream out(file, std::ios::binary);
  out << text;
  ASSERT_TRUE(out.flush()) << "cannot write " << file;
}

inline bool contains(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

}  // namespace mpm::test
