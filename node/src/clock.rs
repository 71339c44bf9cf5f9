//! The capturing machine's clocks, as live camera sources and the node's
//! status need them (`docs/time.md`): the wall clock every capture stamp is
//! on, the offset that moves a driver's `CLOCK_MONOTONIC` buffer time onto
//! it, and what the kernel says of the clock's NTP/PTP discipline.
//!
//! This is the one place in the node library that reads the machine's
//! clocks: a live camera's frames are stamped when and where they are
//! captured; everything downstream takes the stamp it is given.

use shoal_proto::messages::ClockSync;

/// UNIX time now, nanoseconds (`CLOCK_REALTIME`).
pub fn wall_now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

#[allow(unsafe_code)] // libc's clock_gettime: no std call reads CLOCK_MONOTONIC as a number.
fn clock_ns(clock: libc::clockid_t) -> Option<i128> {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec for the call's duration.
    let rc = unsafe { libc::clock_gettime(clock, &mut ts) };
    (rc == 0).then(|| ts.tv_sec as i128 * 1_000_000_000 + ts.tv_nsec as i128)
}

/// `CLOCK_REALTIME − CLOCK_MONOTONIC` now, nanoseconds: add it to a
/// monotonic time to get the wall-clock time of the same instant. Read as the
/// tighter of three bracketed samples, so it is off by well under a
/// microsecond (plus whatever the wall clock is stepped by later).
pub fn realtime_minus_monotonic_ns() -> Option<i128> {
    (0..3)
        .filter_map(|_| {
            let m0 = clock_ns(libc::CLOCK_MONOTONIC)?;
            let r = clock_ns(libc::CLOCK_REALTIME)?;
            let m1 = clock_ns(libc::CLOCK_MONOTONIC)?;
            Some((m1 - m0, r - (m0 + m1) / 2))
        })
        .min_by_key(|(width, _)| *width)
        .map(|(_, offset)| offset)
}

/// What the kernel says of the clock's discipline (`adjtimex(2)` with no
/// change requested), as chrony, ntpd or linuxptp's `phc2sys` maintain it;
/// `None` where it cannot be read.
#[allow(unsafe_code)] // libc's adjtimex: std has no call for the kernel's NTP state.
pub fn kernel_clock_sync() -> Option<ClockSync> {
    // SAFETY: an all-zero `timex` is a valid argument; `modes` 0 only reads.
    let mut tx: libc::timex = unsafe { std::mem::zeroed() };
    // SAFETY: `tx` is a valid, writable timex for the call's duration.
    let state = unsafe { libc::adjtimex(&mut tx) };
    if state < 0 {
        return None;
    }
    // `offset` is in microseconds unless STA_NANO says nanoseconds.
    let offset_ns = if tx.status & libc::STA_NANO != 0 {
        tx.offset as i64
    } else {
        (tx.offset as i64).saturating_mul(1000)
    };
    let us = |v: libc::c_long| (v.max(0) as u64).saturating_mul(1000);
    Some(ClockSync {
        synchronised: state != libc::TIME_ERROR && tx.status & libc::STA_UNSYNC == 0,
        offset_ns,
        est_error_ns: us(tx.esterror),
        max_error_ns: us(tx.maxerror),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn monotonic_moved_by_the_offset_is_the_wall_clock() {
        let offset = realtime_minus_monotonic_ns().unwrap();
        let mono = clock_ns(libc::CLOCK_MONOTONIC).unwrap();
        let wall = wall_now_ns() as i128;
        // Read one after the other: a few microseconds apart on a loaded machine.
        assert!((mono + offset - wall).abs() < 50_000_000);
    }

    #[test]
    fn the_kernel_clock_state_reads_on_linux() {
        let s = kernel_clock_sync().expect("adjtimex reads on Linux");
        // The kernel caps maxerror at NTP_PHASE_LIMIT (16 s).
        assert!(s.max_error_ns <= 16_000_000_000, "{s:?}");
    }
}
