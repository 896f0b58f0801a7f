fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out_dir = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    tonic_prost_build::configure()
        // Frame payloads as `Bytes`: a client keeps unacknowledged frames for resending without copies.
        .bytes(".stillmap.v1.Frame")
        // For gRPC server reflection.
        .file_descriptor_set_path(out_dir.join("stillmap_descriptor.bin"))
        .compile_protos(&["stillmap.proto"], &["."])?;
    println!("cargo:rerun-if-changed=stillmap.proto");
    Ok(())
}
