// Small order statistics shared across the core.
#pragma once

#include <algorithm>
#include <cstddef>
#include <vector>

namespace posecal {

// The median of `v` (for an even count, the upper of the two middle values); 0 when empty.
inline double median(std::vector<double> v) {
  if (v.empty()) return 0;
  const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

}  // namespace posecal
