//! A script of arbitrary datagrams, waits and control choices into `FriClient`.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| isochron_fuzz::client_on_datagram(data));
