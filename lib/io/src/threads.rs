//! Thread priorities: a build that runs beside an interactive view (`mortar build --preview`)
//! gives way to the view's frame thread.
//!
//! With every core busy building, a frame thread that sleeps to the next 60 Hz deadline waits
//! for a time slice when it wakes (measured on the 16-core device: frames of 20-60 ms with a
//! 1 ms draw). Lowering the builder's threads' priority (nice +5 on Linux: about a third of the
//! weight of a normal thread) lets the frame thread run when it wakes, while the build keeps
//! every cycle the view does not use: on an otherwise idle machine the nice value changes only
//! who runs first, not how much the build gets.

/// Lowers the calling thread's scheduling priority (nice +5 on Linux; elsewhere nothing). A
/// failure is ignored: the thread then runs at its normal priority.
pub fn lower_priority() {
    #[cfg(target_os = "linux")]
    {
        // Under Linux, a nice value belongs to a thread (task); PRIO_PROCESS with the thread's id
        // sets that thread's alone.
        // SAFETY: gettid and setpriority take plain integers and touch no memory of ours.
        unsafe {
            let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
            let now = libc::getpriority(libc::PRIO_PROCESS, tid);
            libc::setpriority(libc::PRIO_PROCESS, tid, (now + 5).min(19));
        }
    }
}

#[cfg(test)]
mod tests {
    #[cfg(target_os = "linux")]
    #[test]
    fn lowers_only_the_calling_thread() {
        let before = unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) };
        let other = std::thread::spawn(|| {
            super::lower_priority();
            let tid = unsafe { libc::syscall(libc::SYS_gettid) } as libc::id_t;
            unsafe { libc::getpriority(libc::PRIO_PROCESS, tid) }
        })
        .join()
        .unwrap();
        assert_eq!(other, (before + 5).min(19));
        let tid = unsafe { libc::syscall(libc::SYS_gettid) } as libc::id_t;
        assert_eq!(unsafe { libc::getpriority(libc::PRIO_PROCESS, tid) }, before);
    }
}
