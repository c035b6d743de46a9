//! Fuzzes the STL reader (see `neural_fields_fuzz::check_readers`).
#![no_main]

use libfuzzer_sys::fuzz_target;
use neural_fields::mesh::MeshFormat;

fuzz_target!(|data: &[u8]| neural_fields_fuzz::check_readers(data, MeshFormat::StlBinary));
