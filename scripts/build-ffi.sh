#!/usr/bin/env bash
# Builds libharmonizer (release: shared and static) and installs the header,
# the libraries, a pkg-config file and a CMake package into a prefix.
#
#   scripts/build-ffi.sh [PREFIX]     # default: target/dist
#
# Then: pkg-config --cflags --libs harmonizer (PKG_CONFIG_PATH=PREFIX/lib/pkgconfig)
# or CMake: find_package(harmonizer) with CMAKE_PREFIX_PATH=PREFIX.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
PREFIX=${1:-$ROOT/target/dist}
mkdir -p "$PREFIX"
PREFIX=$(cd "$PREFIX" && pwd)

cargo build --release -p harmonizer-ffi
TARGET_DIR=${CARGO_TARGET_DIR:-$ROOT/target}
VERSION=$(sed -n 's/^#define HZ_VERSION_STRING "\(.*\)"$/\1/p' ffi/include/harmonizer.h)
MAJOR=${VERSION%%.*}
# SHARED_FILE is the installed file, SHARED_SONAME what a consumer records
# (the CMake package's IMPORTED_LOCATION and IMPORTED_SONAME).
case "$(uname -s)" in
    Darwin) SHARED=libharmonizer.dylib SHARED_FILE=libharmonizer.dylib SHARED_SONAME=@rpath/libharmonizer.dylib ;;
    *) SHARED=libharmonizer.so SHARED_FILE=libharmonizer.so.$VERSION SHARED_SONAME=libharmonizer.so.$MAJOR ;;
esac
STATIC=libharmonizer.a
# The system libraries the Rust static library needs (rustc's native-static-libs).
STATIC_LIBS=$(cargo rustc --release -q -p harmonizer-ffi --lib --crate-type staticlib -- --print native-static-libs 2>&1 |
    sed -n 's/.*native-static-libs: //p' | tail -n 1)
STATIC_LIBS=${STATIC_LIBS:--lpthread -ldl -lm}

install -d "$PREFIX/include" "$PREFIX/lib/pkgconfig" "$PREFIX/lib/cmake/harmonizer"
install -m 644 ffi/include/harmonizer.h "$PREFIX/include/"
if [[ $SHARED == *.so ]]; then
    # The soname is libharmonizer.so.MAJOR (ffi/build.rs): the real file carries
    # the full version, with the usual links for the loader and the linker.
    install -m 755 "$TARGET_DIR/release/$SHARED" "$PREFIX/lib/$SHARED.$VERSION"
    ln -sfn "$SHARED.$VERSION" "$PREFIX/lib/$SHARED.$MAJOR"
    ln -sfn "$SHARED.$MAJOR" "$PREFIX/lib/$SHARED"
else
    install -m 755 "$TARGET_DIR/release/$SHARED" "$PREFIX/lib/"
fi
install -m 644 "$TARGET_DIR/release/$STATIC" "$PREFIX/lib/"
subst() {
    sed -e "s|@PREFIX@|$PREFIX|g" -e "s|@VERSION@|$VERSION|g" -e "s|@VERSION_MAJOR@|$MAJOR|g" \
        -e "s|@SHARED_FILE@|$SHARED_FILE|g" -e "s|@SHARED_SONAME@|$SHARED_SONAME|g" -e "s|@STATIC_NAME@|$STATIC|g" -e "s|@STATIC_LIBS@|$STATIC_LIBS|g" "$1"
}
subst ffi/harmonizer.pc.in >"$PREFIX/lib/pkgconfig/harmonizer.pc"
subst cmake/harmonizer-config.cmake.in >"$PREFIX/lib/cmake/harmonizer/harmonizer-config.cmake"
subst cmake/harmonizer-config-version.cmake.in >"$PREFIX/lib/cmake/harmonizer/harmonizer-config-version.cmake"
# The Python binding with its library where the wheel carries it
# (harmonizer/lib/, found without HARMONIZER_LIB); `pip install PREFIX/python`
# builds a wheel from it (hatch_build.py takes the library as it is).
install -d "$PREFIX/python/harmonizer/lib"
install -m 644 ffi/python/harmonizer/*.py ffi/python/harmonizer/py.typed "$PREFIX/python/harmonizer/"
install -m 644 ffi/python/pyproject.toml ffi/python/hatch_build.py ffi/python/README.md "$PREFIX/python/"
install -m 755 "$TARGET_DIR/release/$SHARED" "$PREFIX/python/harmonizer/lib/"
echo "installed libharmonizer $VERSION into $PREFIX"
