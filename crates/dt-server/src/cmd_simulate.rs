//! `shocktwin simulate`: a dyno campaign from the truth plant (`dt-sim`),
//! one MCAP log per run, runs in parallel.

use anyhow::Context as _;
use dt_sim::{
    simulate_campaign_with, simulate_dyno_csv_campaign, simulate_leak_history, CampaignSpec,
    LeakHistorySpec,
};

use crate::cli::{SimFormat, SimulateArgs};

/// Runs `shocktwin simulate`.
pub fn run(args: &SimulateArgs) -> anyhow::Result<()> {
    if args.pressures.is_empty() || args.frequencies.is_empty() {
        anyhow::bail!("simulate: --pressures and --frequencies need at least one value each");
    }
    let started = std::time::Instant::now();
    let summaries = if let (Some(days), Some(leak)) = (args.days, args.leak_rate) {
        let spec = LeakHistorySpec {
            start_bar: args.start_bar,
            leak_bar_per_day: leak,
            days,
            frequency_hz: args.frequencies[0],
            seed: args.seed,
            quick: args.quick,
            unit: args.unit,
            asset_id: args.asset_id.clone(),
            road: args.road.map(|speed_kmh| dt_sim::RoadDrive {
                speed_kmh,
                class: args.road_class,
                seed: args.seed,
            }),
        };
        let bar = crate::progress::bar(u64::from(days), "simulate");
        let done =
            simulate_leak_history(&spec, &args.out, &|s| tick(&bar, s)).with_context(|| {
                format!(
                    "simulate: {days} days of a unit losing {leak} bar/day into {}",
                    args.out.display()
                )
            })?;
        bar.finish_and_clear();
        done
    } else {
        campaign(args)?
    };
    report(&summaries, started, args);
    Ok(())
}

fn campaign(args: &SimulateArgs) -> anyhow::Result<Vec<dt_sim::RunSummary>> {
    let spec = CampaignSpec {
        pressures_bar: args.pressures.clone(),
        frequencies_hz: args.frequencies.clone(),
        seed: args.seed,
        quick: args.quick,
        unit: args.unit,
        repeat: args.repeat,
        road: args.road.map(|speed_kmh| dt_sim::RoadDrive {
            speed_kmh,
            class: args.road_class,
            seed: args.seed,
        }),
        truth_velocity_hz: args.truth_velocity_hz,
        drive_seed: args.drive_seed,
        rig_seed: args.rig_seed,
        ..CampaignSpec::paper(args.seed)
    };
    let bar = crate::progress::bar(spec.runs().len() as u64, "simulate");
    let done = match args.format {
        SimFormat::Mcap => simulate_campaign_with(&spec, &args.out, &|s| tick(&bar, s)),
        SimFormat::DynoCsv => {
            simulate_dyno_csv_campaign(&spec, args.csv_rate_hz, &args.out, &|s| tick(&bar, s))
        }
    }
    .with_context(|| format!("simulate: campaign into {}", args.out.display()));
    bar.finish_and_clear();
    done
}

/// One run written: the bar moves on and names it.
fn tick(bar: &indicatif::ProgressBar, s: &dt_sim::RunSummary) {
    bar.set_message(s.run_id.clone());
    bar.inc(1);
}

fn report(summaries: &[dt_sim::RunSummary], started: std::time::Instant, args: &SimulateArgs) {
    for s in summaries {
        let file = s
            .path
            .as_ref()
            .map_or_else(|| s.run_id.clone(), |p| p.display().to_string());
        crate::outln!(
            "{file}: {:.0} s ({:.0} s excitation, ended by {}), shock thermocouple {:.1} C, oil {:.1} C, {} {}{}",
            s.duration_s,
            s.excitation_s,
            s.stop,
            s.final_shock_reading_c,
            s.final_oil_c,
            s.messages,
            if args.format == SimFormat::DynoCsv { "rows" } else { "messages" },
            if s.cavitation_s > 0.0 {
                format!(", cavitating {:.0} s", s.cavitation_s)
            } else {
                String::new()
            }
        );
    }
    let total_s: f64 = summaries.iter().map(|s| s.duration_s).sum();
    crate::outln!(
        "SIMULATED DATA (dt-sim truth plant, not a real dyno): {} run{} of {}, {:.0} s simulated in {:.1} s, written to {}",
        summaries.len(),
        if summaries.len() == 1 { "" } else { "s" },
        summaries.first().map_or("-", |s| s.asset_id.as_str()),
        total_s,
        started.elapsed().as_secs_f64(),
        args.out.display()
    );
}
