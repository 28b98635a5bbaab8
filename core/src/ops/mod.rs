//! Image operations of the classical pipeline: inpainting, insert
//! harmonization, contact shadows, temporal stabilization.
