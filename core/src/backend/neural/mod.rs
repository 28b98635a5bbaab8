//! The neural backend: an ONNX model run through ONNX Runtime (`ort`,
//! loaded dynamically), described by a JSON manifest.

use std::sync::Arc;

use super::{Backend, BackendInput, Carry, Progress, Stages};
use crate::device::{DeviceOptions, ModelSource};
use crate::error::{Error, Result};
use crate::frame::Image;

/// A loaded model, shared by the sessions of a device.
#[derive(Debug)]
pub struct NeuralModel {
    /// Model name from the manifest.
    pub name: String,
    /// Model version from the manifest.
    pub version: String,
}

impl NeuralModel {
    /// Loads the model the options name; `Ok(None)` for `Embedded` when this
    /// build embeds no model.
    pub fn load(options: &DeviceOptions) -> Result<Option<Arc<NeuralModel>>> {
        match &options.model {
            ModelSource::Embedded => Ok(None),
            _ => Err(Error::Model("loading ONNX models is not wired yet".into())),
        }
    }
}

/// The neural backend over a loaded model.
#[derive(Debug)]
pub struct Neural {
    /// The model.
    pub model: Arc<NeuralModel>,
}

impl Backend for Neural {
    fn name(&self) -> &str {
        "neural"
    }

    fn process(
        &self,
        _input: &BackendInput<'_>,
        _carry: &mut Carry,
        _progress: &mut Progress<'_>,
        _stages: &mut Stages,
    ) -> Result<Image> {
        Err(Error::Model("the neural backend is not wired yet".into()))
    }
}
