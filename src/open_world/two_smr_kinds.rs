//! `two-smr-kinds` — two kinds of SMR in one campaign.
//!
//! A campaign short of reflectors borrows from another kit: some nests hold
//! SMRs of another make or size (a 0.5-inch among 1.5-inch ones, a glass
//! prism among air-path corner cubes). The tracker applies one reflector
//! constant — the offset from the ball's centre to the optical vertex, and
//! for glass the extra optical path — to all of them, so every reading of
//! the other kind is off in range by the difference `c` of the constants:
//!
//! ```text
//! Δd = c        on every reading of a reflector of the other kind
//! ```
//!
//! The same `c` at every station and incidence: not the catalogue's
//! `incidence` (which grows with the incidence angle) nor its per-station
//! `range-scale`.
//!
//! Magnitudes: 30–50 % of the reflectors, `|c|` 5–40 µm (vertex and glass
//! constants of commercial SMRs differ by tens of µm; a kit's are matched to
//! a few).
//!
//! Factor `reflector`: a property of the reflector alone.

use super::{Context, between, index, log_uniform, sign};
use crate::simulate::SimulatedCampaign;
use rand::rngs::ChaCha8Rng;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TwoSmrKinds {
    /// The reflectors of the other kind, sorted.
    pub targets: Vec<String>,
    pub offset_um: f64,
}

impl TwoSmrKinds {
    /// A random 30–50 % of the reflectors (at least one), `|c|`
    /// log-uniform in 5–40 µm with a random sign.
    pub fn draw(rng: &mut ChaCha8Rng, ctx: &Context) -> Result<TwoSmrKinds, String> {
        if ctx.targets.is_empty() {
            return Err("two-smr-kinds needs reflectors".into());
        }
        let n = ctx.targets.len();
        let share = between(rng, 0.3, 0.5);
        let k = ((share * n as f64).round() as usize).clamp(1, n);
        // A partial Fisher–Yates shuffle: the first k of a random order.
        let mut ids: Vec<String> = ctx.targets.iter().map(|t| t.0.clone()).collect();
        for i in 0..k {
            let j = i + index(rng, n - i);
            ids.swap(i, j);
        }
        ids.truncate(k);
        ids.sort();
        Ok(TwoSmrKinds {
            targets: ids,
            offset_um: sign(rng) * log_uniform(rng, 5.0, 40.0),
        })
    }

    pub fn describe(&self) -> String {
        format!(
            "c = {:.1} µm on {} reflectors ({})",
            self.offset_um,
            self.targets.len(),
            self.targets.join(", ")
        )
    }

    pub(super) fn apply(&self, sim: &mut SimulatedCampaign) -> Result<(), String> {
        for t in &self.targets {
            super::target(&sim.targets, t)?;
        }
        for r in &mut sim.campaign.readings {
            if self.targets.contains(&r.target) {
                super::move_reading(r, 0.0, 0.0, self.offset_um * 1e-3);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::{OpenEffect, fixture};
    use super::*;
    use crate::random::stream;

    #[test]
    fn only_the_chosen_reflectors_move_and_by_exactly_c() {
        let sim = fixture::campaign(true);
        let chosen = vec![sim.targets[2].0.clone(), sim.targets[7].0.clone()];
        let e = TwoSmrKinds {
            targets: chosen.clone(),
            offset_um: 25.0,
        };
        let out = OpenEffect::TwoSmrKinds(e).apply(&sim, None).unwrap();
        let mut moved = 0;
        for (a, b) in out.campaign.readings.iter().zip(&sim.campaign.readings) {
            if chosen.contains(&b.target) {
                moved += 1;
                assert_eq!((a.az_deg, a.el_deg), (b.az_deg, b.el_deg));
                assert_eq!(a.d_mm, b.d_mm + 25.0 * 1e-3);
            } else {
                assert_eq!(a, b);
            }
        }
        assert!(moved >= 2);
    }

    #[test]
    fn an_unknown_reflector_is_an_error() {
        let sim = fixture::campaign(true);
        let e = TwoSmrKinds {
            targets: vec!["T99".into()],
            offset_um: 10.0,
        };
        let err = OpenEffect::TwoSmrKinds(e).apply(&sim, None).unwrap_err();
        assert_eq!(err, "reflector `T99` is not in the campaign");
    }

    #[test]
    fn draws_lie_in_the_documented_ranges() {
        let ctx = Context::of(&fixture::campaign(true));
        let n = ctx.targets.len() as f64;
        let mut rng = stream(3, "two-smr-kinds");
        for _ in 0..1000 {
            let e = TwoSmrKinds::draw(&mut rng, &ctx).unwrap();
            let share = e.targets.len() as f64;
            // 30–50 % of 12, rounded: 4 to 6.
            assert!(share >= (0.3 * n).round() && share <= (0.5 * n).round());
            assert!(
                e.targets.windows(2).all(|w| w[0] < w[1]),
                "sorted, distinct"
            );
            assert!(
                e.targets
                    .iter()
                    .all(|t| ctx.targets.iter().any(|x| &x.0 == t))
            );
            assert!((5.0..=40.0).contains(&e.offset_um.abs()));
        }
    }
}
