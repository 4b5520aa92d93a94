//! Arbitrary bytes into the monitoring decoder (the client's side of the wire).
#![no_main]

use std::cell::RefCell;

use libfuzzer_sys::fuzz_target;
use rt_core::fri::{FriVersion, MonitoringDecoder, MonitoringEncoder};

thread_local! {
    // Kept across inputs, as the session keeps it across datagrams.
    // FRI 1.15 (bare protobuf) and 2.7 (length + CRC-32 framing).
    static CODECS: RefCell<[(MonitoringDecoder, MonitoringEncoder); 2]> = RefCell::new(
        [FriVersion::V1_15, FriVersion::V2_7]
            .map(|v| (MonitoringDecoder::with_version(v), MonitoringEncoder::with_version(v))),
    );
}

fuzz_target!(|data: &[u8]| {
    CODECS.with_borrow_mut(|codecs| {
        for (dec, enc) in codecs {
            isochron_fuzz::monitoring_decode(dec, enc, data);
        }
    });
});
