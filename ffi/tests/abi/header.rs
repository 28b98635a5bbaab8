//! The committed header equals what cbindgen generates from the sources, and
//! its version macros equal Cargo.toml's version.

use std::path::{Path, PathBuf};

fn manifest_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn header_path() -> PathBuf {
    manifest_dir().join("include").join("harmonizer.h")
}

/// Generates the header text from `ffi/src` and `ffi/cbindgen.toml`.
pub fn generate() -> String {
    let dir = manifest_dir();
    let config =
        cbindgen::Config::from_file(dir.join("cbindgen.toml")).expect("read ffi/cbindgen.toml");
    let version = format!(
        "\n/** Version of this header (from Cargo.toml). */\n\
         #define HZ_VERSION_MAJOR {}\n#define HZ_VERSION_MINOR {}\n#define HZ_VERSION_PATCH {}\n\
         #define HZ_VERSION_STRING \"{}\"\n",
        env!("CARGO_PKG_VERSION_MAJOR"),
        env!("CARGO_PKG_VERSION_MINOR"),
        env!("CARGO_PKG_VERSION_PATCH"),
        env!("CARGO_PKG_VERSION"),
    );
    let bindings = cbindgen::Builder::new()
        .with_config(config)
        .with_src(dir.join("src").join("lib.rs"))
        .with_after_include(version)
        .generate()
        .expect("cbindgen failed");
    let mut out = Vec::new();
    bindings.write(&mut out);
    String::from_utf8(out).expect("header is UTF-8")
}

fn write_if_blessing(path: &Path, text: &str) -> bool {
    if std::env::var_os("HZ_BLESS_HEADER").is_some() {
        std::fs::write(path, text).expect("write header");
        return true;
    }
    false
}

#[test]
fn header_is_up_to_date() {
    let generated = generate();
    let path = header_path();
    if write_if_blessing(&path, &generated) {
        return;
    }
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    if committed != generated {
        let tmp = std::env::temp_dir().join("harmonizer.generated.h");
        std::fs::write(&tmp, &generated).ok();
        panic!(
            "{} is out of date with ffi/src (generated version: {}).\n\
             Regenerate: HZ_BLESS_HEADER=1 cargo test -p harmonizer-ffi --test abi header",
            path.display(),
            tmp.display()
        );
    }
}

#[test]
fn header_version_macros_match_cargo_toml() {
    let text = std::fs::read_to_string(header_path()).expect("read the committed header");
    let define = |name: &str| -> String {
        text.lines()
            .find_map(|l| l.strip_prefix(&format!("#define {name} ")))
            .unwrap_or_else(|| panic!("harmonizer.h lacks #define {name}"))
            .trim()
            .to_string()
    };
    // Cargo.toml's version, read from the file itself (not through Cargo's env).
    let toml = std::fs::read_to_string(manifest_dir().join("..").join("Cargo.toml"))
        .expect("read Cargo.toml");
    let version = toml
        .lines()
        .skip_while(|l| l.trim() != "[workspace.package]")
        .find_map(|l| l.trim().strip_prefix("version = "))
        .expect("[workspace.package] version in Cargo.toml")
        .trim_matches('"')
        .to_string();
    let parts: Vec<&str> = version.split('.').collect();
    assert_eq!(define("HZ_VERSION_MAJOR"), parts[0]);
    assert_eq!(define("HZ_VERSION_MINOR"), parts[1]);
    assert_eq!(
        define("HZ_VERSION_PATCH"),
        parts[2].split(['-', '+']).next().unwrap()
    );
    assert_eq!(define("HZ_VERSION_STRING"), format!("\"{version}\""));
}
