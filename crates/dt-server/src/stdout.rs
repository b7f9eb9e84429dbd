//! What the commands print for the user, written so that a closed pipe
//! (`shocktwin import … | head`) ends the printing, not the work.
//!
//! `println!` panics when standard output is a pipe whose reader has gone;
//! Rust ignores SIGPIPE, so the write fails with `BrokenPipe` instead of the
//! process dying quietly as a C program would. A command half through its
//! files must still finish them (the reports are a courtesy; the files are
//! the work), so the first failed write stops all further printing, says so
//! once on standard error unless the pipe was merely closed, and lets the
//! command go on.

use std::fmt;
use std::io::{self, Write};
use std::sync::atomic::{AtomicBool, Ordering};

/// Set by the first write that failed: nothing is printed after it.
static GONE: AtomicBool = AtomicBool::new(false);

/// Writes `args` to standard output and flushes it; after a failed write,
/// does nothing. Use through [`outln!`](crate::outln) and [`out!`](crate::out).
pub fn write(args: fmt::Arguments<'_>) {
    if GONE.load(Ordering::Relaxed) {
        return;
    }
    let mut out = io::stdout().lock();
    if let Err(err) = out.write_fmt(args).and_then(|()| out.flush()) {
        if !GONE.swap(true, Ordering::Relaxed) && err.kind() != io::ErrorKind::BrokenPipe {
            eprintln!("shocktwin: standard output: {err}; printing no more (the work goes on)");
        }
    }
}

/// `println!` that survives a closed standard output (see the module).
#[macro_export]
macro_rules! outln {
    () => { $crate::stdout::write(format_args!("\n")) };
    ($($arg:tt)*) => { $crate::stdout::write(format_args!("{}\n", format_args!($($arg)*))) };
}

/// `print!` that survives a closed standard output (see the module).
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => { $crate::stdout::write(format_args!($($arg)*)) };
}
