//! Model manifests and the embedded default model.
