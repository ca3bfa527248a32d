//! A flood of unauthenticated connections does not grow the scheduler: 32
//! connections each announce a 64 MiB frame before any handshake and send
//! 62 MiB of it. With authenticated frames' limit before the handshake,
//! eight such connections took a scheduler from 6 to 299 MiB resident; with
//! the handshake's own 2 KiB limit its peak stays near where it started.
//! Memory is the kernel's count for the scheduler's process (VmHWM).

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::process::{Command, Stdio};

/// The process's peak resident memory, in MiB.
fn peak_mib(pid: u32) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("proc status");
    let kb: u64 = s
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .expect("VmHWM")
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .expect("a number");
    kb / 1024
}

#[test]
fn unauthenticated_frames_cannot_grow_the_scheduler() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_locus"))
        .args(["scheduler", "--listen", "127.0.0.1:0", "--token", "flood"])
        .env("RUST_LOG", "error")
        .stdout(Stdio::piped())
        .spawn()
        .expect("scheduler");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let addr = line
        .trim()
        .rsplit(' ')
        .next()
        .expect("listening on ADDR")
        .to_string();
    let before = peak_mib(child.id());
    let floods: Vec<_> = (0..32)
        .map(|_| {
            let addr = addr.clone();
            std::thread::spawn(move || {
                let Ok(mut s) = TcpStream::connect(&addr) else {
                    return;
                };
                let chunk = vec![0u8; 1 << 20];
                let _ = s.write_all(&((64u32 << 20) - 16).to_be_bytes());
                for _ in 0..62 {
                    // The scheduler closes the connection once it has
                    // read the length: later writes fail, as they should.
                    if s.write_all(&chunk).is_err() {
                        return;
                    }
                }
            })
        })
        .collect();
    for f in floods {
        f.join().unwrap();
    }
    let after = peak_mib(child.id());
    eprintln!("scheduler peak resident memory: {before} MiB before the flood, {after} MiB after");
    let _ = child.kill();
    let _ = child.wait();
    assert!(
        after <= before + 16,
        "scheduler peak grew from {before} to {after} MiB under the flood"
    );
}
