//! Network namespaces for the real-host fault tests: two sides, each a
//! namespace joined to the root namespace by a veth pair, with no route
//! between them (the root namespace does not forward), so the only path from
//! one side to the other is a relay process in the root namespace. And child
//! processes that are killed, and namespaces that are deleted, when the
//! guard drops — on panic too.

#![allow(dead_code)] // each test binary uses a different part

use std::ffi::OsStr;
use std::net::Ipv4Addr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

const PREFIX: &str = "shoalf";

fn ip(args: &[&str]) -> Result<(), String> {
    let out = Command::new("ip")
        .args(args)
        .output()
        .map_err(|e| format!("cannot run `ip`: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "`ip {}` failed: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

/// Namespaces left by a test process that was killed before its guard ran.
fn remove_orphans() {
    let Ok(out) = Command::new("ip").args(["netns", "list"]).output() else {
        return;
    };
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let name = line.split_whitespace().next().unwrap_or("");
        let Some(rest) = name.strip_prefix(PREFIX) else {
            continue;
        };
        let pid: String = rest.chars().skip(1).collect();
        if pid.parse::<u32>().is_ok() && !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = ip(&["netns", "del", name]);
        }
    }
}

/// One side: a namespace `name`, reached from the root namespace at `gateway`,
/// with address `addr` inside.
#[derive(Debug, Clone)]
pub struct Side {
    pub name: String,
    pub addr: Ipv4Addr,
    pub gateway: Ipv4Addr,
    veth: String,
}

/// Two sides; deleted on drop.
#[derive(Debug)]
pub struct TwoNamespaces {
    pub a: Side,
    pub b: Side,
}

impl TwoNamespaces {
    /// Create both sides, or say why not (then the caller skips).
    pub fn create() -> Result<TwoNamespaces, String> {
        remove_orphans();
        let pid = std::process::id();
        // 10.X.Y.0/30 for side a and 10.X.Y+4.0/30 for side b, from the pid.
        let x = 100 + (pid / 32) % 150;
        let y = (pid % 32) * 8;
        let mut made: Vec<Side> = Vec::new();
        for (tag, base) in [("a", y), ("b", y + 4)] {
            let side = Side {
                name: format!("{PREFIX}{tag}{pid}"),
                addr: Ipv4Addr::new(10, x as u8, base as u8, 2),
                gateway: Ipv4Addr::new(10, x as u8, base as u8, 1),
                veth: format!("sf{tag}{pid}"),
            };
            let result = setup(&side);
            made.push(side);
            if let Err(e) = result {
                for s in &made {
                    teardown(s);
                }
                return Err(e);
            }
        }
        let b = made.pop().unwrap();
        let a = made.pop().unwrap();
        Ok(TwoNamespaces { a, b })
    }
}

fn setup(s: &Side) -> Result<(), String> {
    let peer = format!("{}p", s.veth);
    ip(&["netns", "add", &s.name])?;
    ip(&[
        "link", "add", &s.veth, "type", "veth", "peer", "name", &peer,
    ])?;
    ip(&["link", "set", &peer, "netns", &s.name])?;
    ip(&["addr", "add", &format!("{}/30", s.gateway), "dev", &s.veth])?;
    ip(&["link", "set", &s.veth, "up"])?;
    ip(&[
        "-n",
        &s.name,
        "addr",
        "add",
        &format!("{}/30", s.addr),
        "dev",
        &peer,
    ])?;
    ip(&["-n", &s.name, "link", "set", &peer, "up"])?;
    ip(&["-n", &s.name, "link", "set", "lo", "up"])?;
    Ok(())
}

fn teardown(s: &Side) {
    let _ = ip(&["link", "del", &s.veth]);
    let _ = ip(&["netns", "del", &s.name]);
}

impl Drop for TwoNamespaces {
    fn drop(&mut self) {
        teardown(&self.a);
        teardown(&self.b);
    }
}

struct Proc {
    name: String,
    child: Child,
    log: PathBuf,
}

/// Child processes by name; every one still running is killed on drop. On
/// panic, the tail of each one's log is printed.
pub struct Procs {
    dir: PathBuf,
    list: Vec<Proc>,
    started: usize,
}

impl Procs {
    pub fn new(dir: &Path) -> Self {
        Self {
            dir: dir.to_path_buf(),
            list: Vec::new(),
            started: 0,
        }
    }

    /// Start `shoal args…` (in namespace `ns` if given); stdout and stderr to `<dir>/<name>.log`.
    pub fn spawn<S: AsRef<OsStr>>(&mut self, name: &str, ns: Option<&str>, args: &[S]) -> u32 {
        self.started += 1;
        let log = self.dir.join(format!("{name}.{}.log", self.started));
        let file = std::fs::File::create(&log).expect("log file");
        let mut cmd = match ns {
            Some(ns) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", ns, env!("CARGO_BIN_EXE_shoal")]);
                c
            }
            None => Command::new(env!("CARGO_BIN_EXE_shoal")),
        };
        cmd.args(args)
            .env("SHOAL_LOG", "info,zenoh=warn")
            .stdin(Stdio::null())
            .stdout(file.try_clone().expect("log file"))
            .stderr(file);
        let child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {name}: {e}"));
        let pid = child.id();
        self.list.retain(|p| p.name != name);
        self.list.push(Proc {
            name: name.to_string(),
            child,
            log,
        });
        pid
    }

    fn get(&mut self, name: &str) -> &mut Proc {
        self.list
            .iter_mut()
            .find(|p| p.name == name)
            .unwrap_or_else(|| panic!("no process {name}"))
    }

    pub fn pid(&mut self, name: &str) -> u32 {
        self.get(name).child.id()
    }

    /// SIGKILL, and reap.
    pub fn kill(&mut self, name: &str) {
        let p = self.get(name);
        let _ = p.child.kill();
        let _ = p.child.wait();
    }

    /// Send a signal (`INT`, `USR1`, …).
    pub fn signal(&mut self, name: &str, signal: &str) {
        let pid = self.pid(name).to_string();
        let ok = Command::new("kill")
            .args([&format!("-{signal}"), &pid])
            .status()
            .is_ok_and(|s| s.success());
        assert!(ok, "cannot send SIG{signal} to {name}");
    }

    /// Wait for a process to exit by itself.
    pub fn wait_exit(&mut self, name: &str, timeout: Duration) -> Option<ExitStatus> {
        let p = self.get(name);
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            if let Ok(Some(s)) = p.child.try_wait() {
                return Some(s);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        None
    }

    /// Still running?
    pub fn running(&mut self, name: &str) -> bool {
        matches!(self.get(name).child.try_wait(), Ok(None))
    }

    pub fn log(&mut self, name: &str) -> String {
        std::fs::read_to_string(&self.get(name).log).unwrap_or_default()
    }
}

impl Drop for Procs {
    fn drop(&mut self) {
        for p in &mut self.list {
            let _ = p.child.kill();
            let _ = p.child.wait();
        }
        if std::thread::panicking() {
            for p in &self.list {
                let text = std::fs::read_to_string(&p.log).unwrap_or_default();
                let tail: Vec<&str> = text.lines().rev().take(15).collect();
                eprintln!("---- {} ({}) ----", p.name, p.log.display());
                for l in tail.iter().rev() {
                    eprintln!("{l}");
                }
            }
        }
    }
}
