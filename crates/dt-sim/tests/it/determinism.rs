//! Determinism: the same seed gives the same bytes, whatever the number of
//! threads; another seed gives other data.

use dt_sim::{simulate_campaign, simulate_run, CampaignSpec, PlantParams, RunSpec};

fn quick(charge_bar: f64, frequency_hz: f64, seed: u64) -> RunSpec {
    RunSpec {
        quick: true,
        ..RunSpec::paper(charge_bar, frequency_hz, seed)
    }
}

#[test]
fn same_seed_same_bytes_other_seed_other_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let p = PlantParams::nominal();
    let a = dir.path().join("a.mcap");
    let b = dir.path().join("b.mcap");
    let c = dir.path().join("c.mcap");
    simulate_run(&quick(4.0, 2.0, 5), &p, &a).unwrap();
    simulate_run(&quick(4.0, 2.0, 5), &p, &b).unwrap();
    simulate_run(&quick(4.0, 2.0, 6), &p, &c).unwrap();
    let (ba, bb, bc) = (
        std::fs::read(&a).unwrap(),
        std::fs::read(&b).unwrap(),
        std::fs::read(&c).unwrap(),
    );
    assert!(ba.len() > 100_000);
    assert!(ba == bb, "same seed, different bytes");
    assert!(ba != bc, "different seeds, same bytes");
}

#[test]
fn campaign_is_independent_of_thread_count() {
    let spec = CampaignSpec {
        pressures_bar: vec![0.5, 12.0],
        frequencies_hz: vec![4.0],
        quick: true,
        ..CampaignSpec::paper(9)
    };
    let dir = tempfile::tempdir().unwrap();
    let mut outputs = Vec::new();
    for threads in [1, 2] {
        let out = dir.path().join(format!("t{threads}"));
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let summaries = pool.install(|| simulate_campaign(&spec, &out)).unwrap();
        assert_eq!(summaries.len(), 2);
        let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(&out)
            .unwrap()
            .map(|e| {
                let e = e.unwrap();
                (
                    e.file_name().to_string_lossy().into_owned(),
                    std::fs::read(e.path()).unwrap(),
                )
            })
            .collect();
        files.sort();
        outputs.push(files);
    }
    assert_eq!(outputs[0].len(), 2);
    assert!(outputs[0] == outputs[1], "1 and 2 threads differ");
}

#[test]
fn a_repeat_take_is_another_realisation_of_the_same_condition_on_the_same_rig() {
    let dir = tempfile::tempdir().unwrap();
    let p = PlantParams::nominal();
    let first = quick(4.0, 2.0, 5);
    let again = RunSpec { repeat: 1, ..first };
    assert_eq!(again.run_id(), "p4.0-f2.0-s5-r1");
    assert_eq!(
        again.metadata().extra.get("repeat").map(String::as_str),
        Some("1")
    );
    let a = dir.path().join("a.mcap");
    let b = dir.path().join("b.mcap");
    simulate_run(&first, &p, &a).unwrap();
    simulate_run(&again, &p, &b).unwrap();
    let (ba, bb) = (std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    assert!(ba != bb, "a repeat take gave the first take's bytes");
}
