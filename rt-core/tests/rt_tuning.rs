//! The real-time measures `serve` and `bench` take (`fri::priority`), in a
//! process of their own (moving every thread off the FRI CPU would slow the
//! other tests' threads): the FRI thread runs on one CPU, the process's other
//! threads on the rest, the memory is locked when the process may lock it.

use std::time::{Duration, Instant};

use rt_core::fri::priority::{self, RtTuning};
use rt_core::fri::{FriClientParams, FriSession, FriSessionParams, HoldPosition};

/// The CPUs a thread of this process may run on (`Cpus_allowed_list`).
fn allowed(task: &str) -> Vec<usize> {
    allowed_at(&format!("/proc/self/task/{task}/status"))
}

/// The CPUs the calling thread may run on.
fn allowed_here() -> Vec<usize> {
    allowed_at("/proc/thread-self/status")
}

fn allowed_at(path: &str) -> Vec<usize> {
    let status = std::fs::read_to_string(path).unwrap();
    let list = status
        .lines()
        .find_map(|l| l.strip_prefix("Cpus_allowed_list:"))
        .unwrap()
        .trim()
        .to_owned();
    let mut cpus = Vec::new();
    for part in list.split(',') {
        match part.split_once('-') {
            Some((a, b)) => cpus.extend(a.parse::<usize>().unwrap()..=b.parse().unwrap()),
            None => cpus.push(part.parse().unwrap()),
        }
    }
    cpus
}

fn task_named(name: &str) -> Option<String> {
    std::fs::read_dir("/proc/self/task")
        .ok()?
        .flatten()
        .find_map(|t| {
            let comm = std::fs::read_to_string(t.path().join("comm")).ok()?;
            (comm.trim() == name).then(|| t.file_name().to_string_lossy().into_owned())
        })
}

#[test]
fn the_fri_thread_has_its_cpu_and_the_others_keep_off_it() {
    assert_eq!(RtTuning::parse("all"), Ok(RtTuning::ALL));
    assert_eq!(RtTuning::parse("none"), Ok(RtTuning::NONE));
    let t = RtTuning::parse("fifo,isolate").unwrap();
    assert!(t.fifo && t.pin && t.isolate && !t.mlock);
    assert_eq!(RtTuning::parse(&t.label()), Ok(t));
    assert!(RtTuning::parse("fifo,fast").unwrap_err().contains("fast"));

    let before = allowed_here();
    priority::configure(RtTuning::ALL);
    let status = priority::enable();
    let fri_cpu = status.fri_cpu.expect("pinned");
    assert_eq!(Some(&fri_cpu), before.last(), "{status:?}");
    let session = FriSession::spawn(
        FriSessionParams {
            bind: std::net::SocketAddr::from(([127, 0, 0, 1], 0)),
            client: FriClientParams::default(),
            ..FriSessionParams::default()
        },
        HoldPosition,
    )
    .unwrap();
    let deadline = Instant::now() + Duration::from_secs(5);
    let fri = loop {
        if let Some(t) = task_named("isochron-fri")
            && allowed(&t) == vec![fri_cpu]
        {
            break t;
        }
        assert!(
            Instant::now() < deadline,
            "the FRI thread never pinned itself"
        );
        std::thread::yield_now();
    };
    if before.len() >= 2 {
        assert!(status.isolated_threads >= 1, "{status:?}");
        let me = allowed_here();
        assert!(!me.contains(&fri_cpu), "{me:?} {status:?}");
        // A thread started now inherits the mask.
        let child = std::thread::Builder::new()
            .name("isochron-rt-test".into())
            .spawn(allowed_here)
            .unwrap()
            .join()
            .unwrap();
        assert!(!child.contains(&fri_cpu), "{child:?}");
        assert!(!fri.is_empty());
    }
    // Root, or an unlimited memlock limit: the memory is locked.
    let vm_lck_kb: u64 = std::fs::read_to_string("/proc/self/status")
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("VmLck:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap();
    assert_eq!(
        status.memory_locked,
        vm_lck_kb > 0,
        "{status:?} VmLck {vm_lck_kb} kB"
    );
    if rustix_root() {
        assert!(status.memory_locked, "{status:?}");
    }
    drop(session);
}

fn rustix_root() -> bool {
    std::fs::read_to_string("/proc/self/status")
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("Uid:"))
        .and_then(|u| u.split_whitespace().nth(1).map(|e| e == "0"))
        .unwrap_or(false)
}
