fn main() -> Result<(), Box<dyn std::error::Error>> {
    tonic_prost_build::configure().compile_protos(&["stillmap.proto"], &["."])?;
    println!("cargo:rerun-if-changed=stillmap.proto");
    Ok(())
}
