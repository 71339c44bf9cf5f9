//! Standard output for every command: [`outln!`](crate::outln) and
//! [`out!`](crate::out) in place of `println!`/`print!`, which panic when
//! the reader of a pipe goes away (`shoal log info x.mcap | head`). A closed
//! stdout ends the output quietly and the command finishes its work (a demo
//! still closes its log); any other write error is reported once on stderr.
//! Standard error goes through [`errln!`](crate::errln), which drops what
//! cannot be written (`shoal detect … 2>&-` must not panic either).

use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};

static CLOSED: AtomicBool = AtomicBool::new(false);
static FAILED: AtomicBool = AtomicBool::new(false);

/// Write `args` to stdout (used by the macros).
pub fn write(args: std::fmt::Arguments<'_>, newline: bool) {
    if CLOSED.load(Ordering::Relaxed) {
        return;
    }
    let mut o = std::io::stdout().lock();
    let res = o
        .write_fmt(args)
        .and_then(|()| if newline { o.write_all(b"\n") } else { Ok(()) })
        .and_then(|()| o.flush());
    match res {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => {
            CLOSED.store(true, Ordering::Relaxed)
        }
        Err(e) => {
            if !FAILED.swap(true, Ordering::Relaxed) {
                crate::errln!("shoal: cannot write to standard output: {e}");
            }
        }
    }
}

/// Whether the reader of standard output has gone away.
pub fn closed() -> bool {
    CLOSED.load(Ordering::Relaxed)
}

/// `println!` that does not panic on a closed stdout.
#[macro_export]
macro_rules! outln {
    () => { $crate::stdout::write(format_args!(""), true) };
    ($($arg:tt)*) => { $crate::stdout::write(format_args!($($arg)*), true) };
}

/// `print!` that does not panic on a closed stdout.
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => { $crate::stdout::write(format_args!($($arg)*), false) };
}

/// Write `args` and a newline to stderr, ignoring failure (used by [`errln!`](crate::errln)).
pub fn write_err(args: std::fmt::Arguments<'_>) {
    let mut e = std::io::stderr().lock();
    let _ = e.write_fmt(args).and_then(|()| e.write_all(b"\n"));
}

/// `eprintln!` that does not panic on a closed stderr.
#[macro_export]
macro_rules! errln {
    ($($arg:tt)*) => { $crate::stdout::write_err(format_args!($($arg)*)) };
}
