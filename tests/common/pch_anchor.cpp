// The program that builds tests/CMakeLists.txt's precompiled header
// (kestrel_test_pch); the test programs reuse its header and never run it.
int main() { return 0; }
