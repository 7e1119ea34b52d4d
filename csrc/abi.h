// The interface between jaxshadow's shadow engine and its Python side, defined once: the engine
// (`engine/*.h`) lays out its endpoint codes with these widths, and the extension module
// (`shadowc.cc`) exports them as `ABI_VERSION` and `CODE_WIDTH`, which
// `jaxshadow/_shadows/abi.py` reads (and checks against the version it speaks, so that a stale
// build is refused instead of misread). No dependencies.
#ifndef JAXSHADOW_ABI_H_
#define JAXSHADOW_ABI_H_

namespace jaxshadow_abi {

// Bumped whenever a function, argument, result or layout below changes.
constexpr int kAbiVersion = 3;

// One endpoint code: [kind, plane 1 (type, a, b), plane 2 (type, a, b)] int32 (`binding.decode_endpoints`).
constexpr int kCodeWidth = 7;

// One boundary run: its two endpoint codes.
constexpr int kRunWidth = 2 * kCodeWidth;

}  // namespace jaxshadow_abi

#endif  // JAXSHADOW_ABI_H_
