//! The one parameter table and unit variation.

use dt_sim::{parameter_table, PlantParams, SimError};

#[test]
fn parameters_md_is_the_generated_table() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("PARAMETERS.md");
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    let generated = parameter_table();
    if committed != generated {
        // Regenerate with: DT_SIM_BLESS=1 cargo test -p dt-sim params
        if std::env::var_os("DT_SIM_BLESS").is_some() {
            std::fs::write(&path, &generated).unwrap();
        } else {
            panic!("PARAMETERS.md differs from parameter_table(); rerun with DT_SIM_BLESS=1");
        }
    }
}

#[test]
fn varied_unit_scatters_by_a_few_per_cent_deterministically() {
    let nominal = PlantParams::nominal();
    let u1 = nominal.varied(1);
    assert_eq!(u1, nominal.varied(1));
    assert_ne!(u1, nominal.varied(2));
    let mut changed = 0;
    for ((a, b), info) in nominal
        .values()
        .iter()
        .zip(u1.values())
        .zip(PlantParams::TABLE)
    {
        let rel = (b / a - 1.0).abs();
        if info.scatter_pct == 0.0 {
            assert!(rel == 0.0, "{} changed", info.name);
        } else {
            assert!(
                rel <= 2.0 * info.scatter_pct / 100.0 + 1e-12,
                "{}: {rel}",
                info.name
            );
            if rel > 0.0 {
                changed += 1;
            }
        }
    }
    assert!(changed > 30, "only {changed} parameters varied");
    u1.validate().unwrap();
}

#[test]
fn validation_names_the_parameter() {
    let mut p = PlantParams::nominal();
    p.g_oil_outer_w_per_k = -1.0;
    let err = p.validate().unwrap_err();
    assert!(matches!(err, SimError::InvalidParameter { .. }));
    assert!(err.to_string().contains("g_oil_outer_w_per_k"), "{err}");
}

#[test]
fn campaign_rejects_values_that_would_share_a_run_id() {
    let dir = tempfile::tempdir().unwrap();
    let spec = dt_sim::CampaignSpec {
        pressures_bar: vec![1.0, 1.04],
        quick: true,
        ..dt_sim::CampaignSpec::paper(1)
    };
    let err = dt_sim::simulate_campaign(&spec, dir.path()).unwrap_err();
    assert!(err.to_string().contains("pressures_bar = 1.04"), "{err}");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}
