//! Gives the shared library the soname `libharmonizer.so.<major>` on Linux
//! (the C ABI's major version, `HZ_VERSION_MAJOR`): programs linked with
//! `-lharmonizer` record that name, and `scripts/build-ffi.sh` installs the
//! usual `libharmonizer.so.<major>.<minor>.<patch>` with the
//! `libharmonizer.so.<major>` and `libharmonizer.so` links.

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    let os = std::env::var("CARGO_CFG_TARGET_OS").unwrap_or_default();
    if os == "linux" {
        let major =
            std::env::var("CARGO_PKG_VERSION_MAJOR").expect("cargo sets CARGO_PKG_VERSION_MAJOR");
        println!("cargo:rustc-cdylib-link-arg=-Wl,-soname,libharmonizer.so.{major}");
    }
}
