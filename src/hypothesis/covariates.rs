//! What a hypothesis may be written over: one reading's covariates, with
//! their units. One table serves the expression parser (the known names),
//! the README and the error that names an unknown variable.

use crate::effects::IncidenceAngles;
use nalgebra::Vector3;

/// A covariate a hypothesis can read.
#[derive(Clone, Debug, PartialEq)]
pub enum Covariate {
    /// One of [`COVARIATES`], by index.
    Named(usize),
    /// `{station=ID}`: 1 on the readings of station ID, else 0.
    StationIs(String),
    /// `{reflector=ID}`: 1 on the readings of reflector ID, else 0.
    ReflectorIs(String),
}

/// A named covariate, its unit and meaning.
#[derive(Clone, Copy, Debug)]
pub struct Named {
    pub name: &'static str,
    pub unit: &'static str,
    pub meaning: &'static str,
}

/// Every named covariate, in the order of the README's table.
pub const COVARIATES: &[Named] = &[
    Named {
        name: "az",
        unit: "rad",
        meaning: "the reading's azimuth",
    },
    Named {
        name: "el",
        unit: "rad",
        meaning: "the reading's elevation",
    },
    Named {
        name: "d",
        unit: "mm",
        meaning: "the reading's distance",
    },
    Named {
        name: "face",
        unit: "1 or 2",
        meaning: "the reading's face",
    },
    Named {
        name: "time_s",
        unit: "s",
        meaning: "`time_s` of readings.csv",
    },
    Named {
        name: "since_station_s",
        unit: "s",
        meaning: "time since the station's first reading",
    },
    Named {
        name: "temperature_c",
        unit: "°C",
        meaning: "`temperature_c` of readings.csv",
    },
    Named {
        name: "alpha",
        unit: "rad",
        meaning: "SMR incidence angle α (effects.md, `incidence`)",
    },
    Named {
        name: "alpha_h",
        unit: "rad",
        meaning: "horizontal incidence angle α_h",
    },
    Named {
        name: "alpha_v",
        unit: "rad",
        meaning: "vertical incidence angle α_v",
    },
    Named {
        name: "x",
        unit: "mm",
        meaning: "the reflector's centre, campaign frame",
    },
    Named {
        name: "y",
        unit: "mm",
        meaning: "",
    },
    Named {
        name: "z",
        unit: "mm",
        meaning: "",
    },
    Named {
        name: "sx",
        unit: "mm",
        meaning: "the station's origin, campaign frame",
    },
    Named {
        name: "sy",
        unit: "mm",
        meaning: "",
    },
    Named {
        name: "sz",
        unit: "mm",
        meaning: "",
    },
];

impl Covariate {
    /// The covariate an `exmex` variable name stands for.
    pub fn parse(name: &str) -> Option<Covariate> {
        if let Some(id) = name.strip_prefix("station=") {
            return Some(Covariate::StationIs(id.trim().to_string()));
        }
        if let Some(id) = name.strip_prefix("reflector=") {
            return Some(Covariate::ReflectorIs(id.trim().to_string()));
        }
        COVARIATES
            .iter()
            .position(|c| c.name == name)
            .map(Covariate::Named)
    }

    /// Its name as written.
    pub fn name(&self) -> String {
        match self {
            Covariate::Named(k) => COVARIATES[*k].name.to_string(),
            Covariate::StationIs(id) => format!("{{station={id}}}"),
            Covariate::ReflectorIs(id) => format!("{{reflector={id}}}"),
        }
    }
}

/// One reading's covariates. In a simulation they are the truth; in a
/// diagnosis the base adjustment's estimates (positions) and the readings
/// themselves.
#[derive(Clone, Debug)]
pub struct Covariates<'a> {
    pub az: f64,
    pub el: f64,
    pub d: f64,
    pub face: f64,
    pub time_s: Option<f64>,
    pub since_station_s: Option<f64>,
    pub temperature_c: Option<f64>,
    pub incidence: Option<IncidenceAngles>,
    /// The reflector's centre and the station's origin, campaign frame (mm).
    pub point: Vector3<f64>,
    pub station_pos: Vector3<f64>,
    pub station: &'a str,
    pub reflector: &'a str,
}

impl Covariates<'static> {
    /// A reading at the origin with nothing recorded: for what reads no
    /// covariate (a magnitude) and for tests.
    pub fn dummy() -> Covariates<'static> {
        Covariates {
            az: 0.0,
            el: 0.0,
            d: 0.0,
            face: 1.0,
            time_s: None,
            since_station_s: None,
            temperature_c: None,
            incidence: None,
            point: Vector3::zeros(),
            station_pos: Vector3::zeros(),
            station: "",
            reflector: "",
        }
    }
}

impl Covariates<'_> {
    /// The value of `c` at this reading; `None` where the campaign does not
    /// record it.
    pub fn value(&self, c: &Covariate) -> Option<f64> {
        let flag = |b: bool| if b { 1.0 } else { 0.0 };
        match c {
            Covariate::StationIs(id) => Some(flag(self.station == id)),
            Covariate::ReflectorIs(id) => Some(flag(self.reflector == id)),
            Covariate::Named(k) => match COVARIATES[*k].name {
                "az" => Some(self.az),
                "el" => Some(self.el),
                "d" => Some(self.d),
                "face" => Some(self.face),
                "time_s" => self.time_s,
                "since_station_s" => self.since_station_s,
                "temperature_c" => self.temperature_c,
                "alpha" => self.incidence.map(|a| a.alpha),
                "alpha_h" => self.incidence.map(|a| a.alpha_h),
                "alpha_v" => self.incidence.map(|a| a.alpha_v),
                "x" => Some(self.point.x),
                "y" => Some(self.point.y),
                "z" => Some(self.point.z),
                "sx" => Some(self.station_pos.x),
                "sy" => Some(self.station_pos.y),
                "sz" => Some(self.station_pos.z),
                other => unreachable!("covariate {other} has no value"),
            },
        }
    }
}
