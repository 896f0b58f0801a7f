fn main() -> Result<(), Box<dyn std::error::Error>> {
    tonic_prost_build::configure()
        // Frame payloads as `Bytes`: a client keeps unacknowledged frames for resending without copies.
        .bytes(".stillmap.v1.Frame")
        .compile_protos(&["stillmap.proto"], &["."])?;
    println!("cargo:rerun-if-changed=stillmap.proto");
    Ok(())
}
