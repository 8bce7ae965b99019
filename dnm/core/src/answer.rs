//! A DNM's answers to switches and applies as the [`Response`]s tools get, written once for
//! every door a request comes in by (the admin socket, the Zenoh command thread).

use dnm_proto::{Response, SwitchRecord};

use crate::DnmError;

/// DNM `dnm`'s answer to a switch.
pub fn switch_answer(dnm: &str, r: Result<SwitchRecord, DnmError>) -> Response {
    match r {
        Ok(s) => Response {
            ok: true,
            revision: Some(s.revision),
            switches: vec![s],
            ..Response::default()
        },
        Err(e) => refused(dnm, &e),
    }
}

/// DNM `dnm`'s answer to an apply: the revision in force.
pub fn apply_answer(dnm: &str, r: Result<u64, DnmError>) -> Response {
    match r {
        Ok(revision) => Response {
            ok: true,
            revision: Some(revision),
            ..Response::default()
        },
        Err(e) => refused(dnm, &e),
    }
}

/// DNM `dnm` refused, and why.
pub fn refused(dnm: &str, e: &DnmError) -> Response {
    Response::error(format!("DNM `{dnm}`: {e}"))
}

/// The answers of several DNMs of one machine as one: the first refusal, else all merged.
pub fn first_refusal_or_all(answers: Vec<Response>) -> Response {
    if let Some(bad) = answers.iter().find(|a| !a.ok) {
        return bad.clone();
    }
    dnm_proto::merge(answers)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refusal_names_the_dnm_and_wins_over_the_others() {
        let ok = apply_answer("a", Ok(4));
        assert_eq!((ok.ok, ok.revision), (true, Some(4)));
        let no = apply_answer("b", Err(DnmError::Stopped));
        assert_eq!(no.error.as_deref(), Some("DNM `b`: the DNM has stopped"));
        let all = first_refusal_or_all(vec![ok.clone(), no.clone()]);
        assert_eq!(all.error, no.error);
        let all = first_refusal_or_all(vec![ok.clone(), apply_answer("c", Ok(4))]);
        assert_eq!((all.ok, all.revision), (true, Some(4)));
    }
}
