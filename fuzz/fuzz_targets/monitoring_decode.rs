//! Arbitrary bytes into the monitoring decoder (the client's side of the wire).
#![no_main]

use std::cell::RefCell;

use libfuzzer_sys::fuzz_target;
use rt_core::fri::{MonitoringDecoder, MonitoringEncoder};

thread_local! {
    // Kept across inputs, as the session keeps it across datagrams.
    static CODEC: RefCell<(MonitoringDecoder, MonitoringEncoder)> =
        RefCell::new((MonitoringDecoder::new(), MonitoringEncoder::new()));
}

fuzz_target!(|data: &[u8]| {
    CODEC.with_borrow_mut(|(dec, enc)| isochron_fuzz::monitoring_decode(dec, enc, data));
});
