//! A script of arbitrary replies, waits and requests into `SimController`.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| isochron_fuzz::sim_on_reply(data));
