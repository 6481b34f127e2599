// Run ids: random (version 4) UUIDs, lower-case hex with dashes, from the kernel's random
// source. Dependency-free (the command line compiles it in, as it does the atomic writer).
#pragma once

#include <string>

namespace posecal {

std::string new_run_id();

}  // namespace posecal
