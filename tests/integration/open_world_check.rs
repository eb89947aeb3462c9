//! The open-world blind check (issue 30, item 3): campaigns with an effect
//! outside the catalogue, diagnosed blind. These tests hold its
//! bookkeeping — factors, counts, determinism, the stage's tables and
//! settings — and print the honesty rates; the rates' targets are asserted
//! in `open_world.rs`.

use ltcal::diagnose::open_check::{self, Case, CaseKind, Rates};
use ltcal::open_world;
use ltcal::stages::open_world_check::OpenWorldCheckStage;
use ltcal::stages::{Context, StageInputs, StageKind};
use ltcal::trackers::TrackerModel;
use std::path::Path;
use std::process::Command;

fn stage(cases: usize, seed: u64) -> OpenWorldCheckStage {
    OpenWorldCheckStage {
        cases,
        seed,
        mc_draws: 5,
        ..toml::from_str("").unwrap()
    }
}

/// Every field of a case, NaN equal to NaN.
fn rows(cases: &[Case]) -> Vec<String> {
    cases.iter().map(|c| format!("{c:?}")).collect()
}

#[test]
fn open_world_cases_carry_their_unknown_and_add_up() {
    let s = stage(30, 30);
    assert!(s.validate().is_empty(), "{:?}", s.validate());
    let cases = open_check::run(&s.plan()).unwrap();
    assert_eq!(cases.len(), 30);
    assert_eq!(
        cases.iter().map(|c| c.case).collect::<Vec<_>>(),
        (0..30).collect::<Vec<_>>()
    );
    for c in &cases {
        assert!(c.signal_chi2.is_finite() && c.signal_chi2 >= 0.0);
        assert_eq!(c.detectable, c.signal_chi2 >= 25.0);
        assert_eq!(c.kind != CaseKind::Unknown, c.known.is_some());
        if c.kind == CaseKind::WrongModelAndEffect {
            // The true model is the unknown; the campaigns declare the
            // default model.
            let truth = TrackerModel::parse(c.unknown).unwrap();
            assert_ne!(truth, TrackerModel::default());
            assert!(
                c.unknown_description
                    .starts_with(&format!("a {} tracker", c.unknown))
            );
            assert!(c.mismatch_named.is_some());
            assert!(!c.distinguishable || c.signal_beyond_catalogue_chi2 >= 25.0);
            continue;
        }
        assert!(c.mismatch_named.is_none());
        let kind = open_world::parse(c.unknown).unwrap();
        assert_eq!(c.unknown_factor, kind.factor(), "case {}", c.case);
        assert!(open_world::FACTORS.contains(&c.unknown_factor));
        assert!(c.unknown_description.starts_with(c.unknown));
        // Never both: "not explained" and "consistent with noise".
        assert!(
            !(c.not_explained && c.catalogue_as_cause),
            "case {}",
            c.case
        );
        assert_eq!(c.factor_correct, c.top_factor == c.unknown_factor);
        assert_eq!(c.clean_readings, c.readings);
        assert!(c.false_blunders + c.spurious_effects <= c.named_set.split(" + ").count());
        if let Some(k) = &c.known {
            assert!(ltcal::effects::kind(&k.effect).is_some_and(|e| !e.alone));
            assert_eq!(k.within_3u.is_some(), k.named);
            assert!(c.named_set.contains(&k.effect) || !k.named);
        }
    }
    // Counts add up: per kind to all, per unknown to all.
    let all = Rates::of(cases.iter());
    let by_kind: Vec<Rates> = CaseKind::ALL
        .iter()
        .map(|k| Rates::of(cases.iter().filter(|c| c.kind == *k)))
        .collect();
    let mut by_unknown: Vec<Rates> = open_world::KINDS
        .iter()
        .map(|u| Rates::of(cases.iter().filter(|c| c.unknown == *u)))
        .collect();
    let wrong = Rates::of(
        cases
            .iter()
            .filter(|c| c.kind == CaseKind::WrongModelAndEffect),
    );
    assert!(wrong.cases > 0 && wrong.mismatch_cases == wrong.detectable_cases);
    by_unknown.push(wrong);
    for parts in [&by_kind, &by_unknown] {
        let sum = |f: fn(&Rates) -> usize| parts.iter().map(f).sum::<usize>();
        assert_eq!(sum(|r| r.cases), all.cases);
        assert_eq!(sum(|r| r.detectable_cases), all.detectable_cases);
        assert_eq!(sum(|r| r.not_explained), all.not_explained);
        assert_eq!(sum(|r| r.catalogue_as_cause), all.catalogue_as_cause);
        assert_eq!(sum(|r| r.false_blunders), all.false_blunders);
        assert_eq!(sum(|r| r.spurious_effects), all.spurious_effects);
        assert_eq!(sum(|r| r.known_named), all.known_named);
        assert_eq!(sum(|r| r.unknown_cases), all.unknown_cases);
        assert_eq!(sum(|r| r.mismatch_named), all.mismatch_named);
    }
    assert_eq!(by_kind[0].with_known, 0);
    assert!(all.known_named <= all.with_known && all.within_3u <= all.known_named);
    assert!(all.detectable_cases <= all.cases);
    eprintln!(
        "open world, {} cases, {} detectable: not explained {:.1} %, catalogue as cause {:.1} %, \
         factor correct {:.1} %, false blunders {:.2} / 1000, spurious {:.2} a case, \
         catalogue named {:.1} % ({} cases), within 3 u {:.1} %",
        all.cases,
        all.detectable_cases,
        100.0 * all.not_explained_rate(),
        100.0 * all.catalogue_as_cause_rate(),
        100.0 * all.factor_correct_rate(),
        all.false_blunders_per_1000(),
        all.spurious_effects_per_case(),
        100.0 * all.catalogue_named_rate(),
        all.with_known,
        100.0 * all.magnitude_within_3u_rate(),
    );
    for (u, r) in open_world::KINDS.iter().zip(&by_unknown) {
        eprintln!("  {u}: {r:?}");
    }
}

/// Each case has its own random stream: one thread or two, and a block
/// of cases on its own, give the same rows.
#[test]
fn open_world_cases_do_not_depend_on_threads_or_blocks() {
    let plan = stage(6, 31).plan();
    let on = |threads: usize, plan: &open_check::Plan| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| open_check::run(plan).unwrap())
    };
    let one = rows(&on(1, &plan));
    assert_eq!(one, rows(&on(2, &plan)));
    let block = open_check::Plan {
        first: 4,
        cases: 2,
        ..plan.clone()
    };
    assert_eq!(one[4..], rows(&on(2, &block))[..]);
}

/// The stage writes its declared columns, one `cases` row a case, and a
/// summary row per kind, over all, and per unknown drawn.
#[test]
fn open_world_check_stage_writes_its_declared_tables() {
    let s = OpenWorldCheckStage {
        unknowns: vec!["adm-cyclic".into(), "two-smr-kinds".into()],
        ..stage(4, 32)
    };
    assert!(s.validate().is_empty());
    let out = s
        .run(
            &Context {
                pipeline: "t",
                stage: "open",
                file_hash: None,
            },
            &StageInputs::default(),
        )
        .unwrap();
    let names: Vec<&str> = out.tables.iter().map(|t| t.0.as_str()).collect();
    assert_eq!(names, OpenWorldCheckStage::OUTPUTS);
    for (name, df) in &out.tables {
        let columns: Vec<String> = df
            .get_column_names()
            .iter()
            .map(|c| c.to_string())
            .collect();
        assert_eq!(
            columns,
            OpenWorldCheckStage::columns(name).unwrap(),
            "{name}"
        );
    }
    let cases = &out.tables[1].1;
    assert_eq!(cases.height(), 4);
    let summary = &out.tables[0].1;
    let unknowns = crate::util::strs(summary, "unknown");
    let kinds = crate::util::strs(summary, "kind");
    let drawn: std::collections::BTreeSet<String> =
        crate::util::strs(cases, "unknown").into_iter().collect();
    let drawn_kinds: std::collections::BTreeSet<String> =
        crate::util::strs(cases, "kind").into_iter().collect();
    assert_eq!(summary.height(), drawn_kinds.len() + 1 + drawn.len());
    assert!(
        unknowns
            .iter()
            .all(|u| u == "all" || drawn.contains(u.as_str()))
    );
    assert_eq!(
        kinds.iter().filter(|k| *k == "all").count(),
        1 + drawn.len()
    );
    let total = crate::util::cell(summary, "kind", "all", "cases");
    assert_eq!(total, 4.0);
}

fn plan_errors(text: &str) -> (i32, String) {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("bad.toml"), text).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_ltcal"))
        .current_dir(dir.path())
        .args(["plan", "bad.toml"])
        .output()
        .unwrap();
    assert!(!Path::new(&dir.path().join("results")).exists());
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// An unknown effect id, a catalogue id that is not an effect, and a kind
/// of case that does not exist are refused at their place.
#[test]
fn open_world_check_refuses_unknown_effects_and_kinds_at_their_place() {
    let (code, err) = plan_errors(
        "[stages.o]\nkind = \"open_world_check\"\n\
         unknowns = [\"adm-cyclic\", \"gremlins\"]\n\
         effects = [\"range-scale\", \"tripod-knock\"]\n",
    );
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("bad.toml:3:27"), "{err}");
    assert!(
        err.contains("`gremlins` is not an open-world effect; one of tripod-knock"),
        "{err}"
    );
    // An open-world id is not a catalogue effect to put beside it.
    assert!(err.contains("bad.toml:4:27"), "{err}");
    assert!(
        err.contains("`tripod-knock` is not an effect to hide"),
        "{err}"
    );
    let (code, err) = plan_errors(
        "[stages.o]\nkind = \"open_world_check\"\nkinds = [\"unknown\", \"unknown-twice\"]\n",
    );
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("bad.toml:3:"), "{err}");
    assert!(err.contains("unknown-twice"), "{err}");
    assert!(err.contains('^'), "{err}");
    // Without catalogue effects, an `unknown-and-effect` case has none to draw.
    let (code, err) = plan_errors("[stages.o]\nkind = \"open_world_check\"\neffects = []\n");
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("bad.toml:3:"), "{err}");
    assert!(
        err.contains("for `unknown-and-effect` and `wrong-model-and-effect` cases"),
        "{err}"
    );
    // The wrong model must be another than the one declared.
    let (code, err) =
        plan_errors("[stages.o]\nkind = \"open_world_check\"\nwrong_model = \"api-tracker3\"\n");
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("bad.toml:3:15"), "{err}");
    assert!(
        err.contains("`wrong_model` must differ from `model`"),
        "{err}"
    );
    let (code, err) = plan_errors(
        "[stages.o]\nkind = \"open_world_check\"\neffects = []\nkinds = [\"unknown\"]\n",
    );
    assert_eq!(code, 0, "{err}");
}
