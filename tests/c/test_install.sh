#!/usr/bin/env bash
# Installs libharmonizer into a fresh prefix (scripts/build-ffi.sh) and builds
# examples/c/enhance_sequence.c the ways a host would: with pkg-config (shared
# and static) and with CMake's find_package(harmonizer) (imported targets
# harmonizer::harmonizer and harmonizer::harmonizer_static); runs each, checks
# that the shared consumers record the soname libharmonizer.so.MAJOR (readelf
# NEEDED) and that the shared library exports only hz_* symbols.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
WORK=$(mktemp -d "${TMPDIR:-/tmp}/harmonizer-install.XXXXXX")
trap 'rm -rf "$WORK"' EXIT
PREFIX=$WORK/prefix
"$ROOT/scripts/build-ffi.sh" "$PREFIX"
EXAMPLE=$ROOT/examples/c/enhance_sequence.c
WARN="-Wall -Wextra -Werror -pedantic"

echo "== soname and links"
MAJOR=$(sed -n 's/^#define HZ_VERSION_MAJOR \([0-9]*\)$/\1/p' "$ROOT/ffi/include/harmonizer.h")
VERSION=$(sed -n 's/^#define HZ_VERSION_STRING "\(.*\)"$/\1/p' "$ROOT/ffi/include/harmonizer.h")
[[ -f "$PREFIX/lib/libharmonizer.so.$VERSION" && ! -L "$PREFIX/lib/libharmonizer.so.$VERSION" ]] ||
    { echo "FAIL: no libharmonizer.so.$VERSION file"; exit 1; }
[[ "$(readlink "$PREFIX/lib/libharmonizer.so.$MAJOR")" == "libharmonizer.so.$VERSION" ]] ||
    { echo "FAIL: libharmonizer.so.$MAJOR is not a link to libharmonizer.so.$VERSION"; exit 1; }
[[ "$(readlink "$PREFIX/lib/libharmonizer.so")" == "libharmonizer.so.$MAJOR" ]] ||
    { echo "FAIL: libharmonizer.so is not a link to libharmonizer.so.$MAJOR"; exit 1; }
soname=$(readelf -d "$PREFIX/lib/libharmonizer.so.$VERSION" | sed -n 's/.*(SONAME).*\[\(.*\)\]/\1/p')
[[ "$soname" == "libharmonizer.so.$MAJOR" ]] || { echo "FAIL: soname '$soname', expected libharmonizer.so.$MAJOR"; exit 1; }
echo "ok: soname $soname, links libharmonizer.so -> .so.$MAJOR -> .so.$VERSION"

echo "== exported symbols"
bad=$(nm -D --defined-only "$PREFIX/lib/libharmonizer.so" | awk '{print $3}' | grep -v '^hz_' || true)
if [[ -n "$bad" ]]; then
    echo "FAIL: libharmonizer.so exports symbols other than hz_*:"; echo "$bad" | head; exit 1
fi
echo "ok: $(nm -D --defined-only "$PREFIX/lib/libharmonizer.so" | grep -c ' hz_') hz_* symbols, nothing else"

echo "== pkg-config"
export PKG_CONFIG_PATH=$PREFIX/lib/pkgconfig
[[ "$(pkg-config --modversion harmonizer)" == "$(sed -n 's/^#define HZ_VERSION_STRING "\(.*\)"$/\1/p' "$ROOT/ffi/include/harmonizer.h")" ]]
# shellcheck disable=SC2046
gcc -std=c99 $WARN "$EXAMPLE" $(pkg-config --cflags --libs harmonizer) -Wl,-rpath,"$PREFIX/lib" -lm -o "$WORK/enhance_pc_shared"
# shellcheck disable=SC2046
gcc -std=c99 $WARN "$EXAMPLE" $(pkg-config --cflags harmonizer) "$PREFIX/lib/libharmonizer.a" \
    $(pkg-config --static --libs-only-l harmonizer | sed 's/-lharmonizer//') -lm -o "$WORK/enhance_pc_static"
mkdir -p "$WORK/frames"
"$WORK/enhance_pc_shared" 6 64 36 "$WORK/frames" | tail -n 2
"$WORK/enhance_pc_static" 3 64 36 | tail -n 1
[[ -s "$WORK/frames/output_0005.pfm" ]]
# Each tool's output is taken whole before it is searched: `tool | grep -q`
# fails under pipefail when grep stops reading early and the tool gets
# SIGPIPE (seen once on the CMake check below).
dynamic=$(readelf -d "$WORK/enhance_pc_shared")
grep -q "NEEDED.*\[libharmonizer.so.$MAJOR\]" <<<"$dynamic" ||
    { echo "FAIL: the shared build does not record libharmonizer.so.$MAJOR"; exit 1; }
static_libs=$(ldd "$WORK/enhance_pc_static")
if grep -q libharmonizer <<<"$static_libs"; then
    echo "FAIL: the static build links libharmonizer.so"; exit 1
fi

echo "== CMake find_package(harmonizer)"
CMAKE=${CMAKE:-$(command -v cmake || true)}
if [[ -z "$CMAKE" && -x "$ROOT/.venv/bin/cmake" ]]; then CMAKE=$ROOT/.venv/bin/cmake; fi
if [[ -z "$CMAKE" ]]; then
    echo "cmake not found: installing it from PyPI into .venv (pip install cmake)"
    "$ROOT/.venv/bin/python" -m pip install -q cmake
    CMAKE=$ROOT/.venv/bin/cmake
fi
"$CMAKE" -S "$ROOT/tests/c/cmake" -B "$WORK/cmake-build" -DCMAKE_PREFIX_PATH="$PREFIX" -DCMAKE_BUILD_TYPE=Release >/dev/null
"$CMAKE" --build "$WORK/cmake-build" >/dev/null
# The imported target names the real file and its soname (IMPORTED_SONAME):
# the consumer records libharmonizer.so.MAJOR, never a path, and runs through
# the build tree's RUNPATH that CMake sets from the imported location.
needed=$(readelf -d "$WORK/cmake-build/enhance_shared" | sed -n 's/.*(NEEDED).*\[\(.*harmonizer.*\)\]/\1/p')
[[ "$needed" == "libharmonizer.so.$MAJOR" ]] ||
    { echo "FAIL: the CMake consumer records '$needed', expected libharmonizer.so.$MAJOR"; exit 1; }
env -u LD_LIBRARY_PATH "$WORK/cmake-build/enhance_shared" 3 64 36 | tail -n 1
loaded=$(env -u LD_LIBRARY_PATH ldd "$WORK/cmake-build/enhance_shared")
grep -q "libharmonizer.so.$MAJOR => $PREFIX/lib/libharmonizer.so.$MAJOR" <<<"$loaded" ||
    { echo "FAIL: the CMake consumer does not load $PREFIX/lib/libharmonizer.so.$MAJOR:"; echo "$loaded"; exit 1; }
echo "ok: the CMake consumer needs libharmonizer.so.$MAJOR and runs"
"$WORK/cmake-build/enhance_static" 3 64 36 | tail -n 1

echo "== Python binding next to its library"
(cd "$WORK" && env -u HARMONIZER_LIB PYTHONPATH="$PREFIX/python" "$ROOT/.venv/bin/python" -c \
    "import harmonizer as hz, numpy as np; s = hz.Session(hz.Device(), backend='bypass'); \
c = np.ones((4, 4, 4), np.float32); assert (s.process(c)[..., :3] == 1).all(); print('ok: python', hz.version())")

echo "== pip install of the installed Python package (a wheel with the library inside)"
"$ROOT/.venv/bin/python" -m pip install -q --no-deps --target "$WORK/site" "$PREFIX/python"
test -f "$WORK/site/harmonizer/lib/$(basename "$(ls "$PREFIX"/python/harmonizer/lib/libharmonizer.* | head -n 1)")" ||
    { echo "FAIL: the wheel does not carry the library"; exit 1; }
(cd "$WORK" && env -u HARMONIZER_LIB PYTHONPATH="$WORK/site" "$ROOT/.venv/bin/python" -c \
    "import harmonizer as hz, numpy as np; assert hz.__file__.startswith('$WORK/site'), hz.__file__; \
s = hz.Session(hz.Device(), backend='bypass'); c = np.ones((4, 4, 4), np.float32); \
assert (s.process(c)[..., :3] == 1).all(); print('ok: pip-installed', hz.__version__, hz.version())")
echo "install test passed"
