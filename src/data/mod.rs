//! Demonstration datasets on disk (one safetensors file per episode + a JSON index).
