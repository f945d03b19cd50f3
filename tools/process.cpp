#include "process.hpp"

#include <fcntl.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>

extern char** environ;  // NOLINT(readability-redundant-declaration): POSIX, for posix_spawnp

namespace mpm::tools {

ProcessResult run_process(const std::vector<std::string>& argv, bool capture) {
  ProcessResult result;
  if (argv.empty()) {
    result.error = "no program";
    return result;
  }
  std::vector<char*> args;
  args.reserve(argv.size() + 1);
  for (const std::string& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  // Close-on-exec: no other program started meanwhile holds the pipe open (the child's copies
  // on its standard output and error, made by dup2, stay open).
  int pipe_ends[2] = {-1, -1};
  if (capture && ::pipe2(pipe_ends, O_CLOEXEC) != 0) {
    result.error = std::strerror(errno);
    return result;
  }
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  if (capture) {
    posix_spawn_file_actions_addclose(&actions, pipe_ends[0]);
    posix_spawn_file_actions_adddup2(&actions, pipe_ends[1], STDOUT_FILENO);
    posix_spawn_file_actions_adddup2(&actions, pipe_ends[1], STDERR_FILENO);
    posix_spawn_file_actions_addclose(&actions, pipe_ends[1]);
  }
  std::fflush(nullptr);  // what this process printed comes before what the child prints
  pid_t pid = 0;
  int spawned = ::posix_spawnp(&pid, args[0], &actions, nullptr, args.data(), environ);
  if (spawned == ENOEXEC && argv[0].find('/') != std::string::npos) {
    // A script without a "#!" line, named by its path: run it with the shell, as execvp() and
    // a shell would (one found on PATH would need its resolved path; none is started so).
    std::vector<char*> shell{const_cast<char*>("/bin/sh")};
    shell.insert(shell.end(), args.begin(), args.end());
    spawned = ::posix_spawn(&pid, shell[0], &actions, nullptr, shell.data(), environ);
  }
  posix_spawn_file_actions_destroy(&actions);
  if (capture) ::close(pipe_ends[1]);
  if (spawned != 0) {
    if (capture) ::close(pipe_ends[0]);
    result.error = std::strerror(spawned);
    return result;
  }
  if (capture) {
    char buffer[4096];
    for (;;) {
      const ssize_t n = ::read(pipe_ends[0], buffer, sizeof buffer);
      if (n > 0) {
        result.output.append(buffer, static_cast<std::size_t>(n));
      } else if (n == 0 || errno != EINTR) {
        break;
      }
    }
    ::close(pipe_ends[0]);
  }
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0) {
    if (errno != EINTR) {
      result.error = std::strerror(errno);
      return result;
    }
  }
  result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return result;
}

}  // namespace mpm::tools
