//! Writes the project's own models into `models/` (or the folder given):
//!
//!     cargo run --example make_models [-- FOLDER]
//!
//! They come from `raybatch::procedural`, so nothing is downloaded; a test checks that the
//! committed files equal what this writes.

fn main() -> std::io::Result<()> {
    let folder = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "models".to_string());
    std::fs::create_dir_all(&folder)?;
    for (name, bytes) in raybatch::procedural::model_files() {
        let path = std::path::Path::new(&folder).join(name);
        std::fs::write(&path, bytes)?;
        println!("wrote {}", path.display());
    }
    Ok(())
}
