//! A small fuzz driver on proptest, shared by the fuzz harnesses of dt-core
//! (`fuzz_decode`) and dt-server (`fuzz_config`, `fuzz_import`, which include
//! this file by path).
//!
//! A harness runs proptest cases in batches until `SHOCKTWIN_FUZZ_CASES`
//! cases or `SHOCKTWIN_FUZZ_SECS` seconds are spent, whichever comes first
//! (the defaults keep `cargo test` short; `make fuzz` raises both). Each case
//! runs in a worker thread with a time limit (`SHOCKTWIN_FUZZ_CASE_SECS`,
//! default 10 s): a panic or a hang is a crash. proptest then shrinks the
//! input, and the driver prints the minimal input with the seed
//! (`SHOCKTWIN_FUZZ_SEED` replays a run) and fails the test. Every harness
//! ends with one line `fuzz <name>: <n> executions, <k> crashes, <t> s, seed <s>`.

use std::str::FromStr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use proptest::strategy::Strategy;
use proptest::test_runner::{Config, RngSeed, TestCaseError, TestError, TestRunner};

/// Cases per proptest runner; the time budget is checked between batches.
const BATCH: u64 = 32;

/// How long a harness may run, from the environment.
#[derive(Debug, Clone, Copy)]
pub struct Budget {
    /// Most cases to run.
    pub cases: u64,
    /// Most wall time to spend (checked between batches).
    pub time: Duration,
    /// Time limit of one case.
    pub case_time: Duration,
    /// Seed of the first batch (batch `k` uses `seed + k`).
    pub seed: u64,
}

fn env_or<T: FromStr>(name: &str, default: T) -> T {
    match std::env::var(name) {
        Ok(v) => v
            .trim()
            .parse()
            .unwrap_or_else(|_| panic!("{name}={v:?} is not a number")),
        Err(_) => default,
    }
}

impl Budget {
    /// `SHOCKTWIN_FUZZ_CASES` (default `default_cases`), `SHOCKTWIN_FUZZ_SECS`
    /// (default 8), `SHOCKTWIN_FUZZ_CASE_SECS` (default 10),
    /// `SHOCKTWIN_FUZZ_SEED` (default: from the clock).
    #[must_use]
    pub fn from_env(default_cases: u64) -> Budget {
        let clock = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        Budget {
            cases: env_or("SHOCKTWIN_FUZZ_CASES", default_cases),
            time: Duration::from_secs_f64(env_or("SHOCKTWIN_FUZZ_SECS", 8.0)),
            case_time: Duration::from_secs_f64(env_or("SHOCKTWIN_FUZZ_CASE_SECS", 10.0)),
            seed: env_or("SHOCKTWIN_FUZZ_SEED", clock ^ u64::from(std::process::id())),
        }
    }
}

/// Runs `check` on values of `strategy` within the budget; fails the test
/// on the first crash (after shrinking), printing the minimal input.
pub fn fuzz<S>(name: &str, default_cases: u64, strategy: &S, check: fn(&S::Value))
where
    S: Strategy,
    S::Value: Send + 'static,
{
    let budget = Budget::from_env(default_cases);
    let start = Instant::now();
    let executions = Arc::new(AtomicU64::new(0));
    let mut cases_run = 0_u64;
    let mut batch = 0_u64;
    while cases_run < budget.cases && (batch == 0 || start.elapsed() < budget.time) {
        let cases = (budget.cases - cases_run).min(BATCH);
        let config = Config {
            cases: cases as u32,
            failure_persistence: None,
            max_shrink_time: 120_000,
            rng_seed: RngSeed::Fixed(budget.seed.wrapping_add(batch)),
            ..Config::default()
        };
        let mut runner = TestRunner::new(config);
        let counter = Arc::clone(&executions);
        let result = runner.run(strategy, |value| {
            counter.fetch_add(1, Ordering::Relaxed);
            run_case(check, value, budget.case_time).map_err(TestCaseError::fail)
        });
        match result {
            Ok(()) => {}
            Err(TestError::Fail(reason, minimal)) => {
                let line = summary(name, &executions, 1, start, budget.seed);
                eprintln!("{line}");
                let text = format!("{minimal:?}");
                panic!(
                    "{line}\ncrash: {reason}\nminimal input (batch {batch}, seed {}): {}",
                    budget.seed.wrapping_add(batch),
                    clip(&text, 20_000)
                );
            }
            Err(TestError::Abort(reason)) => panic!("fuzz {name}: proptest aborted: {reason}"),
        }
        cases_run += cases;
        batch += 1;
    }
    eprintln!("{}", summary(name, &executions, 0, start, budget.seed));
}

fn summary(name: &str, executions: &AtomicU64, crashes: u32, start: Instant, seed: u64) -> String {
    format!(
        "fuzz {name}: {} executions, {crashes} crashes, {:.1} s, seed {seed}",
        executions.load(Ordering::Relaxed),
        start.elapsed().as_secs_f64()
    )
}

fn clip(text: &str, max: usize) -> &str {
    match text.char_indices().nth(max) {
        Some((i, _)) => &text[..i],
        None => text,
    }
}

/// Runs one case in a worker thread: `Err` names a panic or a hang.
fn run_case<V: Send + 'static>(check: fn(&V), value: V, limit: Duration) -> Result<(), String> {
    let (tx, rx) = mpsc::channel();
    let worker = std::thread::Builder::new()
        .name("fuzz-case".into())
        .spawn(move || {
            check(&value);
            let _ = tx.send(());
        })
        .map_err(|e| format!("cannot start a worker thread: {e}"))?;
    match rx.recv_timeout(limit) {
        Ok(()) => {
            let _ = worker.join();
            Ok(())
        }
        Err(RecvTimeoutError::Timeout) => Err(format!(
            "no result within {limit:?}: a hang (the worker is left running)"
        )),
        Err(RecvTimeoutError::Disconnected) => Err(match worker.join() {
            Err(payload) => format!("panic: {}", panic_text(payload.as_ref())),
            Ok(()) => "the worker ended without a result".into(),
        }),
    }
}

fn panic_text(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_owned()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "(a non-string panic payload)".into()
    }
}
