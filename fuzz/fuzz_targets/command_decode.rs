//! Arbitrary bytes into the command decoder (the controller's side of the wire).
#![no_main]

use std::cell::RefCell;

use libfuzzer_sys::fuzz_target;
use rt_core::fri::{CommandDecoder, CommandEncoder};

thread_local! {
    // Kept across inputs, as the simulated controller keeps it across datagrams.
    static CODEC: RefCell<(CommandDecoder, CommandEncoder)> =
        RefCell::new((CommandDecoder::new(), CommandEncoder::new()));
}

fuzz_target!(|data: &[u8]| {
    CODEC.with_borrow_mut(|(dec, enc)| isochron_fuzz::command_decode(dec, enc, data));
});
