//! The classical backend: hole filling, insert harmonization, contact
//! shadows and temporal stabilization (see `crate::ops`).

use super::{Backend, BackendInput, Carry, Progress, Stages};
use crate::error::Result;
use crate::frame::Image;

/// The classical pipeline.
#[derive(Debug, Default)]
pub struct Classical;

impl Backend for Classical {
    fn name(&self) -> &str {
        "classical"
    }

    fn process(
        &self,
        input: &BackendInput<'_>,
        carry: &mut Carry,
        progress: &mut Progress<'_>,
        stages: &mut Stages,
    ) -> Result<Image> {
        // Placeholder wiring until the ops land: behave as bypass.
        super::Bypass.process(input, carry, progress, stages)
    }
}
