// ThreadSanitizer's suppressions, compiled into every test of the tsan build
// (a suppressions file in TSAN_OPTIONS would not reach gtest's test discovery,
// which runs each binary at build time). Only third-party code is suppressed:
// Debian's libOpenNI2 unlocks a mutex it never locked in its own start-up
// code, and is loaded by any test that links the drivers, whether it opens a
// device or not.
extern "C" const char* __tsan_default_suppressions() { return "called_from_lib:libOpenNI2.so\n"; }
