#pragma once
// Counts the heap allocations a test binary makes (every malloc-family call: operator new,
// Eigen's dynamic matrices and TBB all end in malloc). Link allocation_counter.cpp into the one
// test executable that uses it: it replaces malloc for the whole program.

#include <cstddef>

namespace mpm::test {

/// Heap allocations (malloc, calloc, realloc, aligned allocations) made so far by any thread.
std::size_t allocations();

}  // namespace mpm::test
