// The ORB extractor's vector paths, written once in OpenCV's universal
// intrinsics (header-only, inline: nothing allocates, nothing is linked),
// which compile to SSE2 on x86-64 and to NEON on AArch64. Without either
// (KESTREL_ORB_SIMD 0) the scalar code runs alone; with them, the scalar code
// is still the reference the tests hold the vector paths to
// (orb_detail::set_vector_paths, test_features_orb).
#pragma once

#include <opencv2/core/hal/intrin.hpp>

#if CV_SIMD128
#define KESTREL_ORB_SIMD 1
#else
#define KESTREL_ORB_SIMD 0
#endif
