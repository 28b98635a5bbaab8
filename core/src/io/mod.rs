//! Files: EXR sequences in the `generic`, `blender` and user-mapped layouts.
