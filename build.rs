//! Compiles in the code fingerprint (see `src/code.rs`): the hash of the
//! sources every cache key carries, so that results of other code are not
//! served.

#[path = "src/code.rs"]
mod code;

fn main() {
    let root = std::path::PathBuf::from(
        std::env::var_os("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"),
    );
    let fingerprint = code::fingerprint(&root).expect("hashing the crate's sources");
    println!("cargo:rustc-env=LTCAL_CODE_FINGERPRINT={fingerprint}");
    // A directory: cargo reruns this script when anything under it changes.
    println!("cargo:rerun-if-changed=src");
    for f in code::TOP_FILES {
        println!("cargo:rerun-if-changed={f}");
    }
}
