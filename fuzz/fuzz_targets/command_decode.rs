//! Arbitrary bytes into the command decoder (the controller's side of the wire).
#![no_main]

use std::cell::RefCell;

use libfuzzer_sys::fuzz_target;
use rt_core::fri::{CommandDecoder, CommandEncoder, FriVersion};

thread_local! {
    // Kept across inputs, as the simulated controller keeps it across datagrams.
    // FRI 1.15 (bare protobuf) and 2.7 (length + CRC-32 framing).
    static CODECS: RefCell<[(CommandDecoder, CommandEncoder); 2]> = RefCell::new(
        [FriVersion::V1_15, FriVersion::V2_7]
            .map(|v| (CommandDecoder::with_version(v), CommandEncoder::with_version(v))),
    );
}

fuzz_target!(|data: &[u8]| {
    CODECS.with_borrow_mut(|codecs| {
        for (dec, enc) in codecs {
            isochron_fuzz::command_decode(dec, enc, data);
        }
    });
});
