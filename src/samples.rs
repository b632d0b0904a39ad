//! Placeholder until the generator lands.

/// One generated sample scene.
pub struct Sample {
    /// File name.
    pub file_name: &'static str,
    /// One-line description.
    pub description: &'static str,
    /// The .gltf text.
    pub gltf: String,
}

/// Every sample scene.
pub fn all() -> Vec<Sample> {
    Vec::new()
}
