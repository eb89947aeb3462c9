//! The bound on every count setting, of every stage kind.
//!
//! A count (`mc_draws`, `max_iters`, `cases`, an effect's `order`, …) sizes
//! allocations and loops: a typo such as `mc_draws = 1_000_000_000` must be
//! refused where it is written, before a run aborts on a 32 GB allocation
//! or spends hours. Kinds check their own, tighter ranges; this bound holds
//! for every integer setting of every kind, including those a kind forgets
//! and those added later. Seeds are integers but not counts (any value is
//! as cheap as another) and are left out.

use super::Invalid;
use serde_json::Value;

/// The largest count any setting may hold: the most cases, draws,
/// iterations or sweep points ltcal supports.
pub const MAX_COUNT: u64 = 100_000;

/// Every integer setting above [`MAX_COUNT`] in a stage's settings (as
/// JSON), named by its dotted path (array elements by index).
pub fn check(settings: &Value) -> Vec<Invalid> {
    let mut out = Vec::new();
    walk("", settings, &mut out);
    out
}

fn walk(path: &str, v: &Value, out: &mut Vec<Invalid>) {
    let child = |k: &dyn std::fmt::Display| {
        if path.is_empty() {
            k.to_string()
        } else {
            format!("{path}.{k}")
        }
    };
    match v {
        Value::Object(m) => {
            for (k, v) in m {
                if k != "seed" {
                    walk(&child(k), v, out);
                }
            }
        }
        Value::Array(a) => {
            for (i, v) in a.iter().enumerate() {
                walk(&child(&i), v, out);
            }
        }
        Value::Number(n) => {
            if let Some(n) = n.as_u64().filter(|&n| n > MAX_COUNT) {
                out.push(Invalid::new(
                    path,
                    format!(
                        "`{path}` must be at most {MAX_COUNT} (ltcal's bound on any count), got {n}"
                    ),
                ));
            }
        }
        _ => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn every_integer_but_a_seed_is_bounded_at_any_depth() {
        let s = json!({
            "seed": 1u64 << 60,
            "mc_draws": 1_000_000_000u64,
            "max_iters": MAX_COUNT,
            "noise": {"sigma_angle_urad": 1e12},
            "stations": [4, 200_000],
            "effects": [{"order": 100_001, "seed": u64::MAX}],
        });
        let fields: Vec<String> = check(&s).into_iter().map(|i| i.field).collect();
        assert_eq!(fields, ["effects.0.order", "mc_draws", "stations.1"]);
        assert_eq!(
            check(&json!({"mc_draws": 1_000_000_000u64}))[0].message,
            "`mc_draws` must be at most 100000 (ltcal's bound on any count), got 1000000000"
        );
    }
}
