//! How the binaries end: one scheme for `superflow-pipeline`, `superflow-trainer` and
//! `superflow-recordings`, so that a scheduler (Slurm, Kubernetes, a shell script) reads
//! every one the same way.
//!
//! | code | meaning |
//! |---:|---|
//! | 0 | done |
//! | 1 | [`FAILED`]: the command could not do its work (bad input, a setting out of range, a file or peer gone); the reason is printed on standard error |
//! | 2 | [`USAGE`]: the command line could not be parsed (clap's own code) |
//! | 3 | [`PEER_FAILED`]: a data-parallel job was aborted because another rank failed or stalled |
//! | 128 + N | [`signalled`]: stopped by signal N (SIGTERM: 143, SIGINT: 130) after saving what it could |

use std::error::Error;
use std::process::ExitCode;

/// The command could not do its work.
pub const FAILED: u8 = 1;
/// The command line could not be parsed.
pub const USAGE: u8 = 2;
/// A data-parallel job was aborted because another rank failed or stalled.
pub const PEER_FAILED: u8 = 3;

/// The code of a stop by signal `signal`.
pub fn signalled(signal: i32) -> u8 {
    u8::try_from(128 + signal.clamp(0, 127)).unwrap_or(u8::MAX)
}

/// `err` and its chain of causes, each after a colon; a cause whose text the message
/// before it already holds is not repeated (many errors show their cause inline).
pub fn describe(err: &(dyn Error + 'static)) -> String {
    let mut text = err.to_string();
    let mut cause = err.source();
    while let Some(c) = cause {
        let part = c.to_string();
        if !text.contains(&part) {
            text.push_str(": ");
            text.push_str(&part);
        }
        cause = c.source();
    }
    text
}

/// Prints `program: err` (with its causes) on standard error; the [`FAILED`] code.
pub fn failed(program: &str, err: &(dyn Error + 'static)) -> ExitCode {
    eprintln!("{program}: {}", describe(err));
    ExitCode::from(FAILED)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, thiserror::Error)]
    #[error("{path}: {source}")]
    struct Inline {
        path: String,
        source: std::io::Error,
    }

    #[derive(Debug, thiserror::Error)]
    #[error("opening the drives")]
    struct Context(#[source] Inline);

    #[test]
    fn a_cause_shown_inline_is_not_repeated() {
        let io = || std::io::Error::new(std::io::ErrorKind::NotFound, "No such file");
        let inline = Inline {
            path: "a.mcap".into(),
            source: io(),
        };
        assert_eq!(describe(&inline), "a.mcap: No such file");
        let wrapped = Context(Inline {
            path: "a.mcap".into(),
            source: io(),
        });
        assert_eq!(
            describe(&wrapped),
            "opening the drives: a.mcap: No such file"
        );
    }

    #[test]
    fn signals_are_128_plus_their_number() {
        assert_eq!(signalled(15), 143);
        assert_eq!(signalled(2), 130);
    }
}
