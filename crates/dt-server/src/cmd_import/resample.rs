//! Rates: a tabular export's samples onto SPEC §2's nominal rates.
//!
//! 1. **Uniform grid.** Dyno loggers stamp samples on a coarse clock (a
//!    300 Hz logger on a 1 ms clock steps 3, 3, 4 ms). The rows are
//!    interpolated linearly onto a uniform grid at the file's mean rate,
//!    rounded to a whole hertz or its mean step to a whole millisecond,
//!    whichever is nearer ([`grid_rate`]; so the rate change below is
//!    rational, and a logger every 2 s stays at 0.5 Hz).
//! 2. **Anti-aliased rate change** to each topic's nominal rate with
//!    rubato's synchronous FFT resampler (band-limited: the spectrum is cut
//!    at the output's Nyquist frequency under a Blackman–Harris window, in
//!    FFT blocks of at least [`MIN_BLOCK_OUT`] output samples; flat within
//!    1 % to 0.8 of the output's Nyquist frequency at every rate change a
//!    test tries, as `scipy.signal.resample_poly` is within 0.2 %). rubato
//!    trims its delay to a whole output sample; any rest is measured by
//!    passing a ramp, exact for this linear filter, and carried in the
//!    output's timestamps (none is left with these blocks). As in
//!    `resample_poly`'s `padtype="line"`, the straight line through the
//!    first and last sample is removed before and restored after, so the
//!    zero padding at the ends adds no step; what is left is the ringing of
//!    a band-limited filter at a cut end: under 1 % of the signal at the end
//!    sample, 2e-4 ten samples in, 1e-5 a hundred in.
//! 3. **Never upsampled.** A topic whose source is slower than its nominal
//!    rate is written at the source's rate (SPEC §2 rates are nominal), and
//!    the import says so.

use anyhow::Context as _;
use rubato::audioadapter::Adapter as _;
use rubato::audioadapter_buffers::direct::SequentialSliceOfVecs;
use rubato::{Fft, FixedSync, Resampler as _};

/// A uniform grid's rate, `num / den` Hz exactly: whole hertz (`den` 1) or
/// a whole-millisecond step (`num` 1000), integers so that the rate changes
/// below are rational.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GridRate {
    /// Samples per `den` seconds.
    pub num: u32,
    /// Seconds per `num` samples.
    pub den: u32,
}

impl GridRate {
    /// A whole number of hertz.
    #[must_use]
    pub fn whole(hz: u32) -> Self {
        Self { num: hz, den: 1 }
    }

    /// The rate, Hz.
    #[must_use]
    pub fn hz(self) -> f64 {
        f64::from(self.num) / f64::from(self.den)
    }

    /// Faster than `hz` (exactly, in integers).
    #[must_use]
    pub fn faster_than(self, hz: u32) -> bool {
        u64::from(self.num) > u64::from(hz) * u64::from(self.den)
    }

    /// Seconds from sample 0 to sample `k`.
    #[must_use]
    pub fn time_s(self, k: f64) -> f64 {
        k * f64::from(self.den) / f64::from(self.num)
    }
}

impl std::fmt::Display for GridRate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.num % self.den == 0 {
            write!(f, "{}", self.num / self.den)
        } else {
            let text = format!("{:.4}", self.hz());
            write!(f, "{}", text.trim_end_matches('0'))
        }
    }
}

/// The grid rate of sample times `t_ns` (strictly increasing, two or
/// more): the file's mean rate rounded to whole hertz or its mean step to a
/// whole millisecond, whichever is nearer. A 300 Hz logger on a 1 ms clock
/// (3, 3, 4 ms steps) is 300 Hz, not a 3 ms step's 333 Hz; a logger every
/// 2 s or 1.5 s is 0.5 Hz or 0.667 Hz, not upsampled to 1 or 2 Hz.
#[must_use]
pub fn grid_rate(t_ns: &[i64]) -> GridRate {
    let (first, last) = (t_ns[0], t_ns[t_ns.len() - 1]);
    let mean_step_s = (last - first) as f64 * 1e-9 / (t_ns.len() - 1) as f64;
    let mean_hz = 1.0 / mean_step_s;
    // `as u32` saturates: a step beyond 49 days is 49 days.
    let whole_hz = mean_hz.round().max(1.0);
    let whole_ms = (mean_step_s * 1e3).round().max(1.0);
    if (whole_hz - mean_hz).abs() <= (1e3 / whole_ms - mean_hz).abs() {
        GridRate::whole(whole_hz as u32)
    } else {
        GridRate {
            num: 1000,
            den: whole_ms as u32,
        }
    }
}

/// `x(t_ns)` linearly interpolated at `t0 + k / rate`, `k = 0..` up to the
/// last sample.
#[must_use]
pub fn to_grid(t_ns: &[i64], x: &[f64], rate: GridRate) -> Vec<f64> {
    let t0 = t_ns[0];
    let span_ns = t_ns[t_ns.len() - 1] - t0;
    // in integers: a row on the grid's last point is on it
    let n = (i128::from(span_ns) * i128::from(rate.num) / (i128::from(rate.den) * 1_000_000_000))
        as usize
        + 1;
    let mut out = Vec::with_capacity(n);
    let mut i = 0;
    for k in 0..n {
        let t = t0 as f64 + rate.time_s(k as f64) * 1e9;
        while i + 2 < t_ns.len() && (t_ns[i + 1] as f64) < t {
            i += 1;
        }
        let (ta, tb) = (t_ns[i] as f64, t_ns[i + 1] as f64);
        let w = ((t - ta) / (tb - ta)).clamp(0.0, 1.0);
        out.push(x[i] + w * (x[i + 1] - x[i]));
    }
    out
}

/// `x` at `rate_in` Hz, band-limited and resampled to `rate_out < rate_in`.
#[derive(Debug, Clone, PartialEq)]
pub struct Downsampled {
    /// The output samples.
    pub values: Vec<f64>,
    /// Output sample `j` is the input at index `j · rate_in / rate_out − lag`.
    pub lag_in_samples: f64,
}

/// Output samples per FFT block at least: the anti-aliasing filter's
/// transition band is a few of the block's bins wide, so its cutoff sits
/// near the output's Nyquist frequency only when the block is long in
/// *output* samples. rubato's default (`Fft::new`) aims at 256 *input*
/// samples a block: 13 output samples at 1 kHz -> 50 Hz, whose filter
/// passed an 8 Hz force at 0.48 of its amplitude.
const MIN_BLOCK_OUT: usize = 512;

/// Input samples per FFT block for `rate_in -> rate_out`.
fn block_in(rate_in: u32, rate_out: u32) -> usize {
    (MIN_BLOCK_OUT * rate_in as usize).div_ceil(rate_out as usize)
}

fn resampler(rate_in: u32, rate_out: u32) -> anyhow::Result<Fft<f64>> {
    let block = block_in(rate_in, rate_out);
    Fft::<f64>::new_custom(
        rate_in as usize,
        rate_out as usize,
        block,
        1,
        1,
        rubato::WindowFunction::BlackmanHarris2,
        FixedSync::Input,
    )
    .with_context(|| format!("resampler {rate_in} Hz -> {rate_out} Hz"))
}

fn process(resampler: &mut Fft<f64>, x: Vec<f64>) -> anyhow::Result<Vec<f64>> {
    let n = x.len();
    let channels = [x];
    let input = SequentialSliceOfVecs::new(&channels, 1, n)
        .map_err(|e| anyhow::anyhow!("resampler input: {e}"))?;
    let output = resampler
        .process_all(&input, n, None)
        .context("resampling")?;
    let mut out = vec![0.0; output.frames()];
    output.copy_from_channel_to_slice(0, 0, &mut out);
    Ok(out)
}

/// The resampler's delay left after rubato's trimming, in input samples:
/// a ramp goes through the (linear, unity-gain) filter unchanged but for
/// the delay, read in the middle of the output.
fn residual_lag(rate_in: u32, rate_out: u32) -> anyhow::Result<f64> {
    // the middle of the output far from both ends' ringing (a block long)
    let n = (4 * block_in(rate_in, rate_out)).max(8192);
    let ramp: Vec<f64> = (0..n).map(|i| i as f64).collect();
    let out = process(&mut resampler(rate_in, rate_out)?, ramp)?;
    let j = out.len() / 2;
    Ok(j as f64 * f64::from(rate_in) / f64::from(rate_out) - out[j])
}

/// `x` at `rate_in` Hz, band-limited and resampled to `rate_out < rate_in`.
pub fn downsample(x: &[f64], rate_in: u32, rate_out: u32) -> anyhow::Result<Downsampled> {
    let n = x.len();
    let (first, last) = (x[0], x[n - 1]);
    let slope = if n > 1 {
        (last - first) / (n - 1) as f64
    } else {
        0.0
    };
    let detrended: Vec<f64> = x
        .iter()
        .enumerate()
        .map(|(i, v)| v - first - slope * i as f64)
        .collect();
    // Below a millionth of a sample the lag is the ramp's rounding: none.
    let lag = Some(residual_lag(rate_in, rate_out)?)
        .filter(|l| l.abs() > 1e-6)
        .unwrap_or(0.0);
    let mut out = process(&mut resampler(rate_in, rate_out)?, detrended)
        .with_context(|| format!("resampling {rate_in} Hz -> {rate_out} Hz"))?;
    let per_out = f64::from(rate_in) / f64::from(rate_out);
    for (j, v) in out.iter_mut().enumerate() {
        *v += first + slope * (j as f64 * per_out - lag);
    }
    // Keep only output samples inside the input's span.
    let keep = (((n - 1) as f64 + lag) / per_out).floor() as usize + 1;
    out.truncate(keep.min(out.len()));
    if lag > 0.0 {
        // The first sample would be before the input's start.
        let skip = (lag / per_out).ceil() as usize;
        out.drain(..skip.min(out.len()));
        return Ok(Downsampled {
            values: out,
            lag_in_samples: lag - skip as f64 * per_out,
        });
    }
    Ok(Downsampled {
        values: out,
        lag_in_samples: lag,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_of_a_jittered_300_hz_clock() {
        // 3, 3, 4 ms steps: 300 Hz on average.
        let t: Vec<i64> = (0..3001)
            .map(|k: i32| ((f64::from(k) * 1000.0 / 300.0).round() as i64) * 1_000_000)
            .collect();
        assert_eq!(grid_rate(&t), GridRate::whole(300));
        let x: Vec<f64> = t.iter().map(|&t| 2.0 + 3.0 * t as f64 * 1e-9).collect();
        let g = to_grid(&t, &x, GridRate::whole(300));
        assert_eq!(g.len(), 3001);
        for (k, v) in g.iter().enumerate() {
            assert!((v - (2.0 + 3.0 * k as f64 / 300.0)).abs() < 1e-9);
        }
    }

    #[test]
    fn a_logger_slower_than_a_few_hertz_keeps_its_step() {
        let every = |step_ms: i64, n: i64| -> Vec<i64> {
            (0..n).map(|k| k * step_ms * 1_000_000).collect()
        };
        // every 2 s and every 1.5 s: not 1 Hz and 2 Hz
        let slow = grid_rate(&every(2000, 20));
        assert_eq!(
            slow,
            GridRate {
                num: 1000,
                den: 2000
            }
        );
        assert_eq!(slow.to_string(), "0.5");
        assert!(!slow.faster_than(1));
        let r = grid_rate(&every(1500, 20));
        assert_eq!((r.to_string(), r.hz()), ("0.6667".to_owned(), 1.0 / 1.5));
        // whole-hertz loggers stay whole hertz (30 Hz is no 33 ms step)
        let t30: Vec<i64> = (0..300).map(|k| k * 1_000_000_000 / 30).collect();
        assert_eq!(grid_rate(&t30), GridRate::whole(30));
        assert_eq!(grid_rate(&every(1000, 10)), GridRate::whole(1));
        // the grid lands on the rows, 2 s apart
        let t = every(2000, 5);
        let x: Vec<f64> = (0..5).map(f64::from).collect();
        assert_eq!(to_grid(&t, &x, slow), x);
    }

    #[test]
    fn passband_kept_and_alias_removed() {
        let (rate_in, rate_out) = (300u32, 100u32);
        let n = 30 * rate_in as usize;
        let w = |f: f64, i: usize, r: u32| {
            (2.0 * std::f64::consts::PI * f * i as f64 / f64::from(r)).sin()
        };
        // 2 Hz signal + a 130 Hz tone that would alias to 30 Hz at 100 Hz.
        let x: Vec<f64> = (0..n)
            .map(|i| 0.04 * w(2.0, i, rate_in) + 0.01 * w(130.0, i, rate_in) + 0.5)
            .collect();
        let y = downsample(&x, rate_in, rate_out).unwrap();
        assert_eq!(y.values.len(), (n - 1) / 3 + 1);
        assert!(y.lag_in_samples.abs() < 1e-6);
        // Away from the ends: the 2 Hz signal to 1e-4 of its amplitude, nothing of the tone.
        let worst = (200..y.values.len() - 200)
            .map(|j| (y.values[j] - (0.04 * w(2.0, j, rate_out) + 0.5)).abs())
            .fold(0.0, f64::max);
        assert!(worst < 4e-6, "worst {worst}");
    }

    /// The gain of tones across the output's band, for the rate changes of
    /// real loggers (a helper's trial found a 1 kHz logger's 8 Hz force at
    /// 0.48 of its amplitude at 50 Hz: rubato's blocks had been too short
    /// for its anti-aliasing filter).
    #[test]
    fn the_passband_is_flat_for_every_logger_rate() {
        for (rate_in, rate_out) in [
            (300u32, 100u32),
            (300, 50),
            (500, 50),
            (1000, 50),
            (1000, 100),
            (2000, 100),
            (2000, 1000),
            (1000, 1),
        ] {
            let secs = (60.0_f64).max(600.0 / f64::from(rate_out));
            let n = (secs * f64::from(rate_in)) as usize;
            let nyquist = f64::from(rate_out) / 2.0;
            for frac in [0.1, 0.3, 0.5, 0.64, 0.8] {
                let f = frac * nyquist;
                let x: Vec<f64> = (0..n)
                    .map(|i| (2.0 * std::f64::consts::PI * f * i as f64 / f64::from(rate_in)).sin())
                    .collect();
                let y = downsample(&x, rate_in, rate_out).unwrap();
                let per_out = f64::from(rate_in) / f64::from(rate_out);
                // away from the ends: the tone's amplitude by least squares
                let m = y.values.len();
                let (a, b) = (m / 5, m - m / 5);
                let (mut ss, mut sy) = (0.0, 0.0);
                for j in a..b {
                    let t = (j as f64 * per_out - y.lag_in_samples) / f64::from(rate_in);
                    let s = (2.0 * std::f64::consts::PI * f * t).sin();
                    ss += s * s;
                    sy += s * y.values[j];
                }
                let gain = sy / ss;
                assert!(
                    (gain - 1.0).abs() < 0.01,
                    "{rate_in} -> {rate_out} Hz: a tone at {f} Hz ({frac} of Nyquist) has gain {gain:.4}"
                );
            }
        }
    }

    #[test]
    fn the_residual_lag_is_carried_exactly() {
        // 300 -> 50 Hz: with rubato's default blocks (256 input samples) a
        // half output sample (3 input samples) was left; with blocks of 512
        // output samples none is, and the output is checked against the
        // signal at the times it carries either way.
        let (rate_in, rate_out) = (300u32, 50u32);
        let n = 60 * rate_in as usize;
        let f = |t: f64| (2.0 * std::f64::consts::PI * 0.5 * t).sin();
        let x: Vec<f64> = (0..n).map(|i| f(i as f64 / f64::from(rate_in))).collect();
        let y = downsample(&x, rate_in, rate_out).unwrap();
        let per_out = f64::from(rate_in) / f64::from(rate_out);
        let err = |j: usize| {
            let t = (j as f64 * per_out - y.lag_in_samples) / f64::from(rate_in);
            (y.values[j] - f(t)).abs()
        };
        let m = y.values.len();
        assert_eq!(m, (n - 1) / 6 + 1);
        // the ringing of a cut end: under 1 % at the end sample, 2e-4 ten
        // samples in, 1e-5 a hundred in; nothing in the middle
        assert!(err(0) < 0.01 && err(m - 1) < 0.01);
        for j in [10, m - 11] {
            assert!(err(j) < 2e-4, "{j}: {}", err(j));
        }
        let worst = (100..m - 100).map(err).fold(0.0, f64::max);
        assert!(worst < 1e-5, "worst {worst}, lag {}", y.lag_in_samples);
        let middle = (m / 3..2 * m / 3).map(err).fold(0.0, f64::max);
        assert!(middle < 1e-9, "middle {middle}");
    }
}
