//! `ltcal kinds <kind>`: a stage kind's settings, read from the one place
//! that validates them — the kind's `serde` derive.
//!
//! The names are the fields the derive hands its deserializer
//! (`deserialize_struct`'s `fields`, exactly what `deny_unknown_fields`
//! accepts), caught by a deserializer that records them and stops; the
//! defaults are the kind's settings deserialized from an empty table and
//! written back as JSON (what the cache key hashes); a name's unit is its
//! suffix (`_mm`, `_urad`, …); its meaning is the field's `///` doc,
//! which the settings struct carries at run time
//! ([`documented::DocumentedFields`], a compile error when a field has
//! none). A second list kept by hand would fall behind the structs; this
//! one cannot.

use super::StageConfig;
use serde::de::{self, Visitor};

/// One setting of a stage kind.
#[derive(Clone, Debug, PartialEq)]
pub struct Setting {
    pub name: String,
    /// `number`, `integer`, `string`, `bool`, `array`, `table`; `optional`
    /// when unset by default; `required` when it has no default; empty when
    /// the kind's defaults cannot be probed.
    pub kind: String,
    /// The default as TOML would write it; empty when none.
    pub default: String,
    /// From the name's suffix; empty when it has none.
    pub unit: &'static str,
    /// What the setting means: its field's doc, on one line.
    pub doc: String,
}

/// The settings of stage kind `kind`, in the struct's order; `None` for an
/// unknown kind.
pub fn settings(kind: &str) -> Option<Vec<Setting>> {
    let kind_name = kind;
    let mut fields: &'static [&'static str] = &[];
    let _ = StageConfig::deserialize(kind, Recorder(&mut fields))?;
    let (defaults, required) = defaults(kind);
    Some(
        fields
            .iter()
            .map(|&name| {
                let d = defaults.as_ref().and_then(|d| d.get(name));
                let (kind, default) = match d {
                    // The kind's defaults could not be probed: the meaning
                    // still says what the setting is.
                    None if defaults.is_none() => (String::new(), String::new()),
                    // Left out of the JSON when unset.
                    None => ("optional".to_string(), String::new()),
                    Some(v) if required.contains(&name) => {
                        (format!("{} (required)", json_kind(v)), String::new())
                    }
                    Some(v) => (json_kind(v).to_string(), toml_text(v)),
                };
                Setting {
                    name: name.to_string(),
                    kind,
                    default,
                    unit: unit(name),
                    doc: StageConfig::setting_doc(kind_name, name)
                        .unwrap_or_default()
                        .split_whitespace()
                        .collect::<Vec<_>>()
                        .join(" "),
                }
            })
            .collect(),
    )
}

/// The kind's settings as an empty table gives them, and the names that
/// table must give: each setting serde reports missing is given a value
/// of the first type it accepts (a string, a number, …; an enum's first
/// variant, from serde's own list of them) until the settings deserialize.
fn defaults(kind: &str) -> (Option<serde_json::Value>, Vec<&'static str>) {
    use serde_json::{Value, json};
    let mut table = serde_json::Map::new();
    let mut required: Vec<&'static str> = Vec::new();
    let candidates = [
        json!(""),
        json!(0),
        json!(0.5),
        json!(false),
        json!([]),
        json!({}),
    ];
    let mut tried = 0;
    let mut fields: &'static [&'static str] = &[];
    let _ = StageConfig::deserialize(kind, Recorder(&mut fields));
    for _ in 0..64 {
        let err = match StageConfig::from_json(kind, Value::Object(table.clone())) {
            Ok(c) => return (Some(c.to_json()), required),
            Err(e) => e.to_string(),
        };
        let quoted = |after: &str| -> Option<String> {
            let rest = &err[err.find(after)? + after.len()..];
            Some(rest.split('`').next()?.to_string())
        };
        if let Some(f) = quoted("missing field `") {
            let Some(&f) = fields.iter().find(|x| **x == f) else {
                break;
            };
            required.push(f);
            tried = 0;
            table.insert(f.to_string(), candidates[0].clone());
        } else if let (Some(v), Some(&last)) = (quoted("expected one of `"), required.last()) {
            table.insert(last.to_string(), Value::String(v));
        } else if let Some(&last) = required.last() {
            tried += 1;
            let Some(next) = candidates.get(tried) else {
                break;
            };
            table.insert(last.to_string(), next.clone());
        } else {
            break;
        }
    }
    (None, required)
}

fn json_kind(v: &serde_json::Value) -> &'static str {
    use serde_json::Value;
    match v {
        Value::Null => "optional",
        Value::Bool(_) => "bool",
        Value::Number(n) if n.is_f64() => "number",
        Value::Number(_) => "integer",
        Value::String(_) => "string",
        Value::Array(_) => "array",
        Value::Object(_) => "table",
    }
}

/// A JSON default as TOML writes it (an inline table for an object).
fn toml_text(v: &serde_json::Value) -> String {
    use serde_json::Value;
    match v {
        Value::Null => String::new(),
        Value::Object(m) if m.values().all(Value::is_null) => "{}".to_string(),
        Value::Object(m) => format!(
            "{{ {} }}",
            m.iter()
                .filter(|(_, v)| !v.is_null())
                .map(|(k, v)| format!("{k} = {}", toml_text(v)))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        Value::Array(a) => format!(
            "[{}]",
            a.iter().map(toml_text).collect::<Vec<_>>().join(", ")
        ),
        other => other.to_string(),
    }
}

/// The unit a name's suffix spells, as ltcal names them everywhere.
pub fn unit(name: &str) -> &'static str {
    const UNITS: &[(&str, &str)] = &[
        ("_mm", "mm"),
        ("_um", "µm"),
        ("_urad", "µrad"),
        ("_deg", "degrees"),
        ("_pct", "%"),
        ("_ppm", "ppm"),
        ("_s", "s"),
        ("_c", "°C"),
    ];
    UNITS
        .iter()
        .find(|(s, _)| name.ends_with(s))
        .map_or("", |(_, u)| u)
}

/// A deserializer that only records the fields a struct asks for.
struct Recorder<'a>(&'a mut &'static [&'static str]);

#[derive(Debug)]
struct Stop;

impl std::fmt::Display for Stop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("fields recorded")
    }
}

impl std::error::Error for Stop {}

impl de::Error for Stop {
    fn custom<T: std::fmt::Display>(_: T) -> Self {
        Stop
    }
}

impl<'de> de::Deserializer<'de> for Recorder<'_> {
    type Error = Stop;

    fn deserialize_any<V: Visitor<'de>>(self, _: V) -> Result<V::Value, Stop> {
        Err(Stop)
    }

    fn deserialize_struct<V: Visitor<'de>>(
        self,
        _name: &'static str,
        fields: &'static [&'static str],
        _: V,
    ) -> Result<V::Value, Stop> {
        *self.0 = fields;
        Err(Stop)
    }

    serde::forward_to_deserialize_any! {
        bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string
        bytes byte_buf option unit unit_struct newtype_struct seq tuple
        tuple_struct map enum identifier ignored_any
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_lists_settings_with_their_units() {
        let with = super::super::KINDS
            .iter()
            .filter(|k| !settings(k).unwrap().is_empty())
            .count();
        // `correct`, `evaluate`, `evaluate_campaign` have none.
        assert_eq!(with, super::super::KINDS.len() - 3);
        let measure = settings("measure").unwrap();
        let seed = measure.iter().find(|s| s.name == "seed").unwrap();
        assert_eq!(seed.kind, "integer");
        assert_eq!(seed.doc, "Seed of the noise draws.");
        // Every setting of every kind says what it means: the derive refuses
        // an undocumented field, and a serde name that is not the field's
        // would find no doc here.
        for k in super::super::KINDS {
            for s in settings(k).unwrap() {
                assert!(!s.doc.is_empty(), "{k}.{} has no doc", s.name);
                // The doc's lines are joined with a space: a word hyphenated
                // across two `///` lines would print as `mirror- tracker`.
                let split = s
                    .doc
                    .as_bytes()
                    .windows(3)
                    .any(|w| w[0].is_ascii_alphanumeric() && w[1] == b'-' && w[2] == b' ');
                assert!(
                    !split,
                    "{k}.{}: a word split at a line end: {}",
                    s.name, s.doc
                );
            }
        }
        assert_eq!(unit("sigma_angle_urad"), "µrad");
        assert!(settings("nope").is_none());
    }
}
