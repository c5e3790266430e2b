// Debian's Abseil (20220623) has its own string_view type, distinct from
// std::string_view: StrCat, CHexEscape and absl's string-keyed maps take
// absl::string_view. V converts, without a copy.
#ifndef FLEETMEM_SERVICES_CORE_ABSL_VIEW_H_
#define FLEETMEM_SERVICES_CORE_ABSL_VIEW_H_

#include <string_view>

#include "absl/strings/string_view.h"

namespace fleetmem {

inline absl::string_view V(std::string_view s) { return {s.data(), s.size()}; }

}  // namespace fleetmem

#endif  // FLEETMEM_SERVICES_CORE_ABSL_VIEW_H_
