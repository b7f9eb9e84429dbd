//! `dt-sim` owns the dyno simulator: the truth plant (a twin-tube damper on a
//! displacement-controlled dyno) and its sensors. It writes shocktwin log v1
//! campaigns through `dt_core::log` and never uses the twin's own models.
