//! "Did you mean …?": the known name nearest to a misspelt one.
//!
//! A misspelt stage kind, stage, table or setting is the most common mistake
//! in a pipeline file, and the list of every known name that the errors
//! already give makes the reader search for the one they meant. One rule
//! for every such error, here, so that they all suggest alike: a name is
//! suggested only when it is a likely typo of the word — within two edits
//! (a swap of neighbours counting as one) and no more than half the word,
//! so that a short word is not "near" everything, or similar by
//! Jaro-Winkler (≥ 0.8, which favours a shared beginning).

/// The known name most likely meant by `word`: the fewest edits away, the
/// most similar among equals, the first among those; `None` when no name is
/// close enough to be a typo.
pub fn nearest<'a>(word: &str, known: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    let len = word.chars().count();
    known
        .into_iter()
        .filter(|k| *k != word)
        .map(|k| {
            let edits = strsim::damerau_levenshtein(word, k);
            (k, edits, strsim::jaro_winkler(word, k))
        })
        .filter(|&(_, edits, similar)| (edits <= 2 && 2 * edits <= len) || similar >= 0.8)
        // `min_by` keeps the first of equals: the order the names were given.
        .min_by(|a, b| a.1.cmp(&b.1).then(b.2.total_cmp(&a.2)))
        .map(|(k, _, _)| k)
}

/// `"; did you mean `name`?"` for the name nearest to `word`, or nothing:
/// for the end of an error message.
pub fn hint<'a>(word: &str, known: impl IntoIterator<Item = &'a str>) -> String {
    nearest(word, known)
        .map(|k| format!("; did you mean `{k}`?"))
        .unwrap_or_default()
}

/// serde's message for an unknown field or variant — "unknown field `stp`,
/// expected one of `shape`, `step`" — with the nearest expected name
/// appended; any other message unchanged. serde builds the message and we
/// cannot reach the names otherwise, so they are read back from its fixed
/// wording (the names are each between backticks after "expected").
pub fn serde_message(message: &str) -> String {
    let Some(rest) = ["unknown field `", "unknown variant `"]
        .iter()
        .find_map(|lead| message.split_once(lead).map(|(_, rest)| rest))
    else {
        return message.to_string();
    };
    let Some((word, rest)) = rest.split_once('`') else {
        return message.to_string();
    };
    let Some((_, expected)) = rest.split_once("expected") else {
        return message.to_string();
    };
    // Between backticks: the odd pieces of a split on them.
    let known = expected.split('`').skip(1).step_by(2);
    format!("{message}{}", hint(word, known))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_typo_is_matched_and_a_stranger_is_not() {
        let kinds = ["mesh", "measure", "identify", "correct"];
        assert_eq!(nearest("meshh", kinds), Some("mesh"));
        assert_eq!(nearest("idnetify", kinds), Some("identify"));
        assert_eq!(nearest("zzz", kinds), None);
        // Two edits are the whole of a two-letter word.
        assert_eq!(nearest("ab", ["xy", "cd"]), None);
    }

    #[test]
    fn the_fewest_edits_win() {
        assert_eq!(
            nearest("identify_plan", ["identify_sphere", "identify_plane"]),
            Some("identify_plane")
        );
    }

    #[test]
    fn serde_messages_get_the_nearest_expected_name() {
        assert_eq!(
            serde_message("unknown field `stp`, expected one of `shape`, `step`"),
            "unknown field `stp`, expected one of `shape`, `step`; did you mean `step`?"
        );
        assert_eq!(
            serde_message("unknown variant `plnae`, expected `plane` or `sphere`"),
            "unknown variant `plnae`, expected `plane` or `sphere`; did you mean `plane`?"
        );
        assert_eq!(
            serde_message("unknown field `x`, there are no fields"),
            "unknown field `x`, there are no fields"
        );
        assert_eq!(serde_message("invalid type"), "invalid type");
    }
}
