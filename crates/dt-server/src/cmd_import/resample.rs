//! Rates: a tabular export's samples onto SPEC §2's nominal rates.
//!
//! 1. **Uniform grid.** Dyno loggers stamp samples on a coarse clock (a
//!    300 Hz logger on a 1 ms clock steps 3, 3, 4 ms). The rows are
//!    interpolated linearly onto a uniform grid at the file's mean rate,
//!    rounded to a whole hertz (so the rate change below is rational).
//! 2. **Anti-aliased rate change** to each topic's nominal rate with
//!    rubato's synchronous FFT resampler (band-limited: the spectrum is cut
//!    at the output's Nyquist frequency under a Blackman–Harris window, the
//!    quality of `scipy.signal.resample_poly`). rubato trims its delay to a
//!    whole output sample; the rest (half an output sample at 300 → 50 Hz)
//!    is measured by passing a ramp, exact for this linear filter, and
//!    carried in the output's timestamps. As in `resample_poly`'s
//!    `padtype="line"`, the straight line through the first and last sample
//!    is removed before and restored after, so the zero padding at the ends
//!    adds no step; what is left is the ringing of a band-limited filter at
//!    a cut end, about ten output samples long (0.2 s at 50 Hz).
//! 3. **Never upsampled.** A topic whose source is slower than its nominal
//!    rate is written at the source's rate (SPEC §2 rates are nominal), and
//!    the import says so.

use anyhow::Context as _;
use rubato::audioadapter::Adapter as _;
use rubato::audioadapter_buffers::direct::SequentialSliceOfVecs;
use rubato::{Fft, FixedSync, Resampler as _};

/// The grid rate of sample times `t_ns` (whole hertz, at least 1).
#[must_use]
pub fn grid_rate_hz(t_ns: &[i64]) -> u32 {
    let (first, last) = (t_ns[0], t_ns[t_ns.len() - 1]);
    let mean_step_s = (last - first) as f64 * 1e-9 / (t_ns.len() - 1) as f64;
    ((1.0 / mean_step_s).round() as u32).max(1)
}

/// `x(t_ns)` linearly interpolated at `t0 + k / rate_hz`, `k = 0..` up to the
/// last sample.
#[must_use]
pub fn to_grid(t_ns: &[i64], x: &[f64], rate_hz: u32) -> Vec<f64> {
    let t0 = t_ns[0];
    let span_ns = t_ns[t_ns.len() - 1] - t0;
    let n = (span_ns as f64 * 1e-9 * f64::from(rate_hz)).floor() as usize + 1;
    let mut out = Vec::with_capacity(n);
    let mut i = 0;
    for k in 0..n {
        let t = t0 as f64 + k as f64 * 1e9 / f64::from(rate_hz);
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

fn resampler(rate_in: u32, rate_out: u32) -> anyhow::Result<Fft<f64>> {
    Fft::<f64>::new(
        rate_in as usize,
        rate_out as usize,
        1024,
        1,
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
    let n = (rate_in as usize * 20).max(8192);
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
        assert_eq!(grid_rate_hz(&t), 300);
        let x: Vec<f64> = t.iter().map(|&t| 2.0 + 3.0 * t as f64 * 1e-9).collect();
        let g = to_grid(&t, &x, 300);
        assert_eq!(g.len(), 3001);
        for (k, v) in g.iter().enumerate() {
            assert!((v - (2.0 + 3.0 * k as f64 / 300.0)).abs() < 1e-9);
        }
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

    #[test]
    fn the_residual_lag_is_carried_exactly() {
        // 300 -> 50 Hz: rubato leaves half an output sample (3 input samples).
        let (rate_in, rate_out) = (300u32, 50u32);
        let n = 60 * rate_in as usize;
        let f = |t: f64| (2.0 * std::f64::consts::PI * 0.5 * t).sin();
        let x: Vec<f64> = (0..n).map(|i| f(i as f64 / f64::from(rate_in))).collect();
        let y = downsample(&x, rate_in, rate_out).unwrap();
        let per_out = f64::from(rate_in) / f64::from(rate_out);
        let worst = (100..y.values.len() - 100)
            .map(|j| {
                let t = (j as f64 * per_out - y.lag_in_samples) / f64::from(rate_in);
                (y.values[j] - f(t)).abs()
            })
            .fold(0.0, f64::max);
        assert!(worst < 1e-6, "worst {worst}, lag {}", y.lag_in_samples);
    }
}
