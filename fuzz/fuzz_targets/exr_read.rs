//! Any bytes as an EXR file, through the reader the CLI uses: the header
//! guard, the decoder, layout detection and the frame description.
#![no_main]

use std::path::Path;

use harmonizer_core::io::exr::{ExrFile, LoadedFrame};
use harmonizer_core::io::guard::ReadLimits;
use harmonizer_core::io::layout::LayoutOptions;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // A budget well below the fuzzer's RSS limit (2 GiB): a claim above it is
    // refused. A tiny DWA file may legitimately claim about 2^17 times its
    // size; the decoded frame, its planar copies and ASan's quarantine must
    // stay under the RSS limit.
    let limits = ReadLimits::with_memory_limit(64 << 20);
    let Ok(file) = ExrFile::from_bytes(data.to_vec(), Path::new("fuzz.exr"), Some(1), &limits)
    else {
        return;
    };
    let _ = file.names();
    let _ = file.parts();
    let _ = file.camera(0);
    if let Ok(frame) = LoadedFrame::from_file(file, &LayoutOptions::default()) {
        let _ = frame.frame_input();
    }
});
