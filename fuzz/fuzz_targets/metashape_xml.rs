#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| xscale_fuzz::check("metashape_xml", data));
