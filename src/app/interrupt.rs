//! SIGINT and SIGTERM during an interactive session (`view`, `xr`): the handler only notes the
//! signal; the session's loop sees it at the next frame and ends as if its frame count were
//! reached, so the recording is finished whole; then [`reraise`] ends the process by the same
//! signal, so the caller (a shell, a test) still sees how it ended.
//!
//! Batch commands (`ao`, `replay`) keep the default action: their outputs are written beside
//! their names and renamed once complete, so dying at once is already clean.

use std::sync::atomic::{AtomicI32, Ordering};

/// The signal caught, 0 while none.
static CAUGHT: AtomicI32 = AtomicI32::new(0);

/// The signals a session ends on.
const SIGNALS: [libc::c_int; 2] = [libc::SIGINT, libc::SIGTERM];

extern "C" fn note(sig: libc::c_int) {
    // Async-signal-safe: one atomic store.
    CAUGHT.store(sig, Ordering::SeqCst);
}

/// From now on the first SIGINT or SIGTERM sets [`caught`] instead of ending the process; a
/// second one ends it. Called once the session's frames begin, so a signal during the
/// precompute still ends it at once.
pub fn catch() {
    for sig in SIGNALS {
        // SA_RESTART: a read or write in flight (the recording's) completes instead of failing.
        // SA_RESETHAND: a second signal ends the process at once, should the session hang.
        // SAFETY: `act` starts all zeroes (a valid sigaction) and `note`, its handler, only
        // stores to an atomic, which is async-signal-safe; sigaction only fails for an invalid
        // signal or a bad pointer, neither possible here.
        unsafe {
            let mut act: libc::sigaction = std::mem::zeroed();
            act.sa_sigaction = note as extern "C" fn(libc::c_int) as libc::sighandler_t;
            act.sa_flags = libc::SA_RESTART | libc::SA_RESETHAND;
            libc::sigemptyset(&mut act.sa_mask);
            libc::sigaction(sig, &act, std::ptr::null_mut());
        }
    }
}

/// The signal caught since [`catch`], if any.
pub fn caught() -> Option<libc::c_int> {
    match CAUGHT.load(Ordering::SeqCst) {
        0 => None,
        sig => Some(sig),
    }
}

/// The signal's name, for messages.
pub fn name(sig: libc::c_int) -> &'static str {
    match sig {
        libc::SIGINT => "SIGINT",
        libc::SIGTERM => "SIGTERM",
        _ => "a signal",
    }
}

/// If a signal was caught, ends the process by it (default action restored); else returns.
pub fn reraise() {
    if let Some(sig) = caught() {
        // SAFETY: signal and raise take plain values; SIG_DFL is a valid disposition and `sig` a
        // signal this process caught.
        unsafe {
            libc::signal(sig, libc::SIG_DFL);
            libc::raise(sig);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_caught_signal_is_noted_not_fatal() {
        catch();
        assert_eq!(caught(), None);
        // SAFETY: the handler catch() installed only stores to an atomic.
        unsafe { libc::raise(libc::SIGTERM) };
        // The handler runs before raise returns (a signal sent to the calling thread).
        assert_eq!(caught(), Some(libc::SIGTERM));
        // The handler is gone after the first signal: a second one would end the process.
        // SAFETY: libc::sigaction is plain C data, for which all zeroes is a valid value.
        let mut now: libc::sigaction = unsafe { std::mem::zeroed() };
        // SAFETY: a null new action only reads the current one into `now`, a live local.
        unsafe { libc::sigaction(libc::SIGTERM, std::ptr::null(), &mut now) };
        assert_eq!(now.sa_sigaction, libc::SIG_DFL);
        assert_eq!(name(libc::SIGTERM), "SIGTERM");
        // Back to the default, so this test binary is not left deaf to Ctrl-C.
        for sig in SIGNALS {
            // SAFETY: restores the default disposition of a valid signal.
            unsafe { libc::signal(sig, libc::SIG_DFL) };
        }
        CAUGHT.store(0, Ordering::SeqCst);
    }
}
