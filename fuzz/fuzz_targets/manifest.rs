//! Any text as a model manifest (`<model>.json`).
#![no_main]

use harmonizer_core::model::Manifest;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = Manifest::from_json(text, "fuzz.json");
    }
});
