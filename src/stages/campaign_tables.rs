//! A campaign as pipeline tables and back, so that stages can pass a whole
//! campaign along (a group input slot, [`campaign::TABLES`]) and the cache can
//! hash it like any other output. It lives with the stages, not in
//! [`crate::campaign`], because it is an adapter between the runner's tables
//! and the domain: the campaign itself knows nothing of stage inputs.
//!
//! The tables mirror the files column for column — `readings` has
//! readings.csv's columns (and `line`, where each reading was read from), `targets` targets.csv's, `gauge` gauge.csv's —
//! with every optional column always present (null where not known), and
//! `meta` holds campaign.toml as one row. The round trip is exact: numbers
//! stay `f64`, angles stay in degrees.

use super::StageInputs;
use crate::campaign::{
    self, Aim, Campaign, CampaignReading, GaugeLength, Issue, Meta, Target, Tracker,
};
use crate::kinematics::Face;
use crate::table::{TableBuilder, TableRef};
use anyhow::{Result, anyhow, bail};
use nalgebra::Vector3;
use polars::prelude::{DataFrame, SeriesTrait};
use std::sync::{Arc, Mutex, Weak};

/// Campaigns that passed [`Campaign::check`] with the tables this process
/// built from them ([`Campaign::checked_tables`]), for as long as the
/// tables live.
static ISSUED: Mutex<Vec<Issued>> = Mutex::new(Vec::new());

/// One checked campaign and its tables' columns, in the order of
/// [`campaign::TABLES`], held weakly: a weak reference keeps a column's
/// allocation from being freed (so no other column can come to sit at its
/// address) without keeping its data, and polars copies a column before it
/// changes one that anything else refers to, weakly or not. A live column at
/// the address kept here is therefore that column, unchanged.
struct Issued {
    columns: Vec<Vec<Weak<dyn SeriesTrait>>>,
    campaign: Arc<Campaign>,
}

impl Issued {
    /// Whether `tables` (in the order of [`campaign::TABLES`]) are these
    /// tables: the same column objects, in the same order, and no others.
    fn is(&self, tables: &[TableRef]) -> bool {
        self.columns.len() == tables.len()
            && self.columns.iter().zip(tables).all(|(kept, t)| {
                let cols = t.df.columns();
                kept.len() == cols.len()
                    && kept.iter().zip(cols).all(|(k, c)| {
                        c.as_series()
                            .is_some_and(|s| std::ptr::addr_eq(k.as_ptr(), Arc::as_ptr(&s.0)))
                    })
            })
    }

    /// Whether some table could still be these: none of its columns is gone.
    fn alive(&self) -> bool {
        self.columns.iter().flatten().all(|k| k.strong_count() > 0)
    }
}

impl Campaign {
    /// `readings`, `targets`, `gauge` and `meta`, in the order of [`campaign::TABLES`].
    pub fn to_tables(&self) -> Result<Vec<(String, DataFrame)>> {
        Ok(vec![
            ("readings".into(), self.readings_table()?),
            ("targets".into(), self.targets_table()?),
            ("gauge".into(), self.gauge_table()?),
            ("meta".into(), self.meta_table()?),
        ])
    }

    /// [`Campaign::to_tables`] of a campaign that passed [`Campaign::check`]
    /// (the `import_campaign` stage's, read from its folder), remembered
    /// ([`ISSUED`], while the tables live) so that [`Campaign::from_inputs`]
    /// given these very tables takes the campaign back instead of rebuilding
    /// and checking it again (issue 34: 4 % of the instructions of the race's
    /// import and calibration of 24 000 readings).
    pub fn checked_tables(c: &Arc<Campaign>) -> Result<Vec<(String, DataFrame)>> {
        let tables = c.to_tables()?;
        let columns = tables
            .iter()
            .map(|(_, df)| {
                df.columns()
                    .iter()
                    .map(|c| Arc::downgrade(&c.as_materialized_series().0))
                    .collect()
            })
            .collect();
        let mut issued = ISSUED.lock().unwrap_or_else(|e| e.into_inner());
        issued.retain(Issued::alive);
        issued.push(Issued {
            columns,
            campaign: Arc::clone(c),
        });
        Ok(tables)
    }

    /// The campaign wired to the group slot `slot` (tables `<slot>.readings`,
    /// `<slot>.targets`, `<slot>.gauge`, `<slot>.meta`), held to the format's
    /// rules: a stage never works on a campaign that could not be written.
    ///
    /// Tables that are the very tables [`Campaign::checked_tables`] built
    /// give back the campaign they were built from, not rebuilt or checked
    /// again. That skips nothing, whatever stage the tables come from: the
    /// rebuild of those tables is that campaign (the round trip is exact,
    /// `a_campaign_rebuilt_from_its_tables_is_the_campaign`), which passed
    /// the same [`Campaign::check`] this would run. Any other tables —
    /// read back from the cache, made by another stage, or the same tables
    /// with a column changed or added — are other column objects
    /// ([`Issued`]), and are rebuilt and checked in full.
    pub fn from_inputs(inputs: &StageInputs, slot: &str) -> Result<Arc<Campaign>> {
        let table = |name: &str| inputs.get(&format!("{slot}.{name}"));
        let tables: Option<Vec<TableRef>> = campaign::TABLES
            .iter()
            .map(|name| inputs.optional(&format!("{slot}.{name}")))
            .collect();
        if let Some(tables) = tables {
            let issued = ISSUED.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(kept) = issued.iter().rev().find(|kept| kept.is(&tables)) {
                return Ok(Arc::clone(&kept.campaign));
            }
        }
        let c = Campaign {
            meta: meta_from(&table("meta")?)?,
            readings: readings_from(&table("readings")?)?,
            targets: targets_from(&table("targets")?)?,
            gauge: gauge_from(&table("gauge")?)?,
        };
        let issues = c.check();
        if !issues.is_empty() {
            let list: Vec<String> = issues.iter().map(Issue::to_string).collect();
            bail!(
                "input `{slot}` is not a valid campaign:\n  {}",
                list.join("\n  ")
            );
        }
        Ok(Arc::new(c))
    }

    fn readings_table(&self) -> Result<DataFrame> {
        let r = &self.readings;
        let stations: Vec<&str> = r.iter().map(|r| r.station.as_str()).collect();
        let targets: Vec<&str> = r.iter().map(|r| r.target.as_str()).collect();
        TableBuilder::new()
            .str("station", &stations)
            .str("target", &targets)
            .f64("az_deg", r.iter().map(|r| r.az_deg).collect())
            .f64("el_deg", r.iter().map(|r| r.el_deg).collect())
            .f64("d_mm", r.iter().map(|r| r.d_mm).collect())
            .i64("face", r.iter().map(|r| r.face.number()).collect())
            .opt_f64("time_s", r.iter().map(|r| r.time_s).collect())
            .opt_f64("temperature_c", r.iter().map(|r| r.temperature_c).collect())
            .opt_f64("pressure_hpa", r.iter().map(|r| r.pressure_hpa).collect())
            .opt_f64("humidity_pct", r.iter().map(|r| r.humidity_pct).collect())
            .opt_i64("line", r.iter().map(|r| r.line.map(|l| l as i64)).collect())
            .build()
    }

    fn targets_table(&self) -> Result<DataFrame> {
        let t = &self.targets;
        let ids: Vec<&str> = t.iter().map(|t| t.id.as_str()).collect();
        let reference = |k: usize| t.iter().map(|t| t.reference.map(|p| p[k])).collect();
        let aim = |k: usize| t.iter().map(|t| t.aim.map(|p| p[k])).collect();
        TableBuilder::new()
            .str("target", &ids)
            .opt_f64("x_mm", reference(0))
            .opt_f64("y_mm", reference(1))
            .opt_f64("z_mm", reference(2))
            .opt_f64("u_mm", t.iter().map(|t| t.u_mm).collect())
            .opt_f64("aim_x_mm", aim(0))
            .opt_f64("aim_y_mm", aim(1))
            .opt_f64("aim_z_mm", aim(2))
            .build()
    }

    fn gauge_table(&self) -> Result<DataFrame> {
        let g = &self.gauge;
        let a: Vec<&str> = g.iter().map(|g| g.target_a.as_str()).collect();
        let b: Vec<&str> = g.iter().map(|g| g.target_b.as_str()).collect();
        TableBuilder::new()
            .str("target_a", &a)
            .str("target_b", &b)
            .f64("distance_mm", g.iter().map(|g| g.distance_mm).collect())
            .opt_f64("u_mm", g.iter().map(|g| g.u_mm).collect())
            .build()
    }

    fn meta_table(&self) -> Result<DataFrame> {
        let m = &self.meta;
        TableBuilder::new()
            .i64("format", vec![m.format])
            .str("name", &[&m.name])
            .str("description", &[&m.description])
            .str("tracker_model", &[&m.tracker.model])
            .opt_f64("sigma_angle_urad", vec![m.tracker.sigma_angle_urad])
            .opt_f64("sigma_range_um", vec![m.tracker.sigma_range_um])
            .opt_f64("sigma_range_ppm", vec![m.tracker.sigma_range_ppm])
            .str("smr_aim", &[m.aim.as_str()])
            .opt_f64("smr_radius_mm", vec![m.smr_radius_mm])
            .build()
    }
}

fn readings_from(t: &TableRef) -> Result<Vec<CampaignReading>> {
    let (station, target) = (t.str("station")?, t.str("target")?);
    let (az, el, d) = (t.f64("az_deg")?, t.f64("el_deg")?, t.f64("d_mm")?);
    let face = t
        .i64("face")?
        .into_iter()
        .enumerate()
        .map(|(i, n)| {
            Face::from_number(n).ok_or_else(|| {
                anyhow!(
                    "table `{}`, column `face`, row {i}: 1 (front) or 2 (back), got {n}",
                    t.name
                )
            })
        })
        .collect::<Result<Vec<Face>>>()?;
    let time = t.opt_f64("time_s")?;
    let temperature = t.opt_f64("temperature_c")?;
    let pressure = t.opt_f64("pressure_hpa")?;
    let humidity = t.opt_f64("humidity_pct")?;
    let line = t.opt_i64("line")?;
    Ok(station
        .into_iter()
        .zip(target)
        .enumerate()
        .map(|(i, (station, target))| CampaignReading {
            station,
            target,
            az_deg: az[i],
            el_deg: el[i],
            d_mm: d[i],
            face: face[i],
            time_s: time[i],
            temperature_c: temperature[i],
            pressure_hpa: pressure[i],
            humidity_pct: humidity[i],
            line: line[i].and_then(|l| usize::try_from(l).ok()),
        })
        .collect())
}

/// Three nullable columns that form one point: all known or all null.
fn points(t: &TableRef, names: [&str; 3]) -> Result<Vec<Option<Vector3<f64>>>> {
    let [x, y, z] = [
        t.opt_f64(names[0])?,
        t.opt_f64(names[1])?,
        t.opt_f64(names[2])?,
    ];
    (0..t.height())
        .map(|i| match (x[i], y[i], z[i]) {
            (Some(x), Some(y), Some(z)) => Ok(Some(Vector3::new(x, y, z))),
            (None, None, None) => Ok(None),
            _ => Err(anyhow!(
                "table `{}`, row {i}: {} go together (all known or all null)",
                t.name,
                names.join(", ")
            )),
        })
        .collect()
}

fn targets_from(t: &TableRef) -> Result<Vec<Target>> {
    let ids = t.str("target")?;
    let reference = points(t, ["x_mm", "y_mm", "z_mm"])?;
    let u = t.opt_f64("u_mm")?;
    let aim = points(t, ["aim_x_mm", "aim_y_mm", "aim_z_mm"])?;
    Ok(ids
        .into_iter()
        .enumerate()
        .map(|(i, id)| Target {
            id,
            reference: reference[i],
            u_mm: u[i],
            aim: aim[i],
        })
        .collect())
}

fn gauge_from(t: &TableRef) -> Result<Vec<GaugeLength>> {
    let (a, b) = (t.str("target_a")?, t.str("target_b")?);
    let distance = t.f64("distance_mm")?;
    let u = t.opt_f64("u_mm")?;
    Ok((0..t.height())
        .map(|i| GaugeLength {
            target_a: a[i].clone(),
            target_b: b[i].clone(),
            distance_mm: distance[i],
            u_mm: u[i],
        })
        .collect())
}

fn meta_from(t: &TableRef) -> Result<Meta> {
    if t.height() != 1 {
        bail!(
            "table `{}` has {} rows; a campaign's meta is one row",
            t.name,
            t.height()
        );
    }
    let aim = t.str("smr_aim")?.remove(0);
    Ok(Meta {
        format: t.i64("format")?[0],
        name: t.str("name")?.remove(0),
        description: t.str("description")?.remove(0),
        tracker: Tracker {
            model: t.str("tracker_model")?.remove(0),
            sigma_angle_urad: t.opt_f64("sigma_angle_urad")?[0],
            sigma_range_um: t.opt_f64("sigma_range_um")?[0],
            sigma_range_ppm: t.opt_f64("sigma_range_ppm")?[0],
        },
        aim: Aim::parse(&aim).ok_or_else(|| {
            anyhow!(
                "table `{}`, column `smr_aim`: \"aim-columns\" or \"stations-centroid\", got \"{aim}\"",
                t.name
            )
        })?,
        smr_radius_mm: t.opt_f64("smr_radius_mm")?[0],
    })
}

/// readings.csv's columns, then the line each reading was read from.
static READINGS_TABLE_COLUMNS: std::sync::LazyLock<Vec<&'static str>> =
    std::sync::LazyLock::new(|| {
        crate::campaign::READINGS_COLUMNS
            .iter()
            .copied()
            .chain(["line"])
            .collect()
    });

/// The columns of a campaign's tables as stages pass them on.
pub fn columns(table: &str) -> Option<&'static [&'static str]> {
    match table {
        "readings" => Some(READINGS_TABLE_COLUMNS.as_slice()),
        "targets" => Some(crate::campaign::TARGETS_COLUMNS),
        "gauge" => Some(crate::campaign::GAUGE_COLUMNS),
        "meta" => Some(&[
            "format",
            "name",
            "description",
            "tracker_model",
            "sigma_angle_urad",
            "sigma_range_um",
            "sigma_range_ppm",
            "smr_aim",
            "smr_radius_mm",
        ]),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::table::{from_parquet_bytes, to_parquet_bytes};
    use polars::prelude::Column;
    use std::path::Path;

    fn example() -> Campaign {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/campaigns/example-00-none");
        crate::campaign::read(&dir).unwrap()
    }

    /// The tables wired to the group slot `campaign`.
    fn inputs(tables: Vec<(String, DataFrame)>) -> StageInputs {
        let mut inputs = StageInputs::default();
        for (name, df) in tables {
            let slot = format!("campaign.{name}");
            inputs.insert(&slot, slot.clone(), Arc::new(df));
        }
        inputs
    }

    /// What lets [`Campaign::from_inputs`] give back the checked campaign for
    /// its own tables: their rebuild (here from tables read back from
    /// Parquet, other column objects) is that campaign, field for field.
    #[test]
    fn a_campaign_rebuilt_from_its_tables_is_the_campaign() {
        let c = example();
        let copies = c
            .to_tables()
            .unwrap()
            .into_iter()
            .map(|(n, df)| {
                (
                    n,
                    from_parquet_bytes(&to_parquet_bytes(&df).unwrap()).unwrap(),
                )
            })
            .collect();
        assert_eq!(
            *Campaign::from_inputs(&inputs(copies), "campaign").unwrap(),
            c
        );
    }

    /// Issue 34: the tables of a checked campaign give that campaign back
    /// (not rebuilt); the same tables with one column changed are rebuilt and
    /// checked — a broken value is refused, not answered with the campaign.
    #[test]
    fn checked_tables_give_their_campaign_back_and_a_changed_column_is_checked() {
        let c = Arc::new(example());
        let tables = Campaign::checked_tables(&c).unwrap();
        let same = Campaign::from_inputs(&inputs(tables.clone()), "campaign").unwrap();
        assert!(Arc::ptr_eq(&same, &c));

        let mut changed = tables;
        let readings = &mut changed[0].1;
        let n = readings.height();
        readings
            .with_column(Column::new("d_mm".into(), vec![-1.0; n]))
            .unwrap();
        let e = Campaign::from_inputs(&inputs(changed), "campaign").unwrap_err();
        assert!(e.to_string().contains("a distance must be > 0"), "{e}");
    }
}
