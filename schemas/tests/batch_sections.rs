//! The section table has one source, `schemas/src/batch/sections.rs`: `BATCH_FORMAT.md`
//! shows it as it renders, and the Python readers name only sections it lists.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests fail loudly on purpose

use std::path::{Path, PathBuf};
use superflow_schemas::batch::Section;
use superflow_schemas::batch::sections::markdown;

const BEGIN: &str = "<!-- sections:begin";
const END: &str = "<!-- sections:end -->";

fn repo_file(relative: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(relative)
}

/// Fails when the table between the markers of `BATCH_FORMAT.md` is not what
/// `sections::markdown()` renders; with `SUPERFLOW_BLESS=1` it rewrites it instead.
#[test]
fn batch_format_md_shows_the_rust_section_table() {
    let path = repo_file("BATCH_FORMAT.md");
    let text = std::fs::read_to_string(&path).unwrap();
    let begin = text
        .find(BEGIN)
        .expect("BATCH_FORMAT.md has the sections:begin marker");
    let start = begin + text[begin..].find('\n').expect("a line after the marker") + 1;
    let end = text
        .find(END)
        .expect("BATCH_FORMAT.md has the sections:end marker");
    assert!(
        start <= end,
        "the sections:end marker comes before sections:begin"
    );
    let expected = markdown();
    if text[start..end] == expected {
        return;
    }
    if std::env::var("SUPERFLOW_BLESS").as_deref() == Ok("1") {
        let blessed = format!("{}{expected}{}", &text[..start], &text[end..]);
        std::fs::write(&path, blessed).unwrap();
        eprintln!("rewrote the section table of {}", path.display());
        return;
    }
    panic!(
        "the section table of {} differs from schemas/src/batch/sections.rs; paste this \
         between the sections:begin and sections:end markers (or run the test with \
         SUPERFLOW_BLESS=1):\n\n{expected}",
        path.display()
    );
}

/// The section names a Python file uses as keys of its arrays or batches
/// (`arrays["points"]`, `arrays.get('l0_nbr')`, `arrays[f"l{l}_nbr"]` with the level
/// read as 0, `batch["images"]`).
fn names_used(python: &str) -> Vec<String> {
    let mut names = Vec::new();
    for opener in ["arrays[", "arrays.get(", "batch["] {
        for (at, _) in python.match_indices(opener) {
            let rest = python[at + opener.len()..].trim_start();
            let rest = rest.strip_prefix('f').unwrap_or(rest);
            let Some(quote) = rest.chars().next().filter(|c| *c == '"' || *c == '\'') else {
                continue; // a variable, not a literal name
            };
            let Some(len) = rest[1..].find(quote) else {
                continue;
            };
            let mut name = String::new();
            let mut in_braces = false;
            for c in rest[1..1 + len].chars() {
                match c {
                    '{' => in_braces = true,
                    '}' => {
                        in_braces = false;
                        name.push('0');
                    }
                    _ if !in_braces => name.push(c),
                    _ => {}
                }
            }
            names.push(name);
        }
    }
    names
}

#[test]
fn python_readers_name_only_sections_of_the_table() {
    let mut used = Vec::new();
    for file in [
        "../tests/python/read_batch.py",
        "../trainer/python/superflow/format.py",
        "../trainer/python/superflow/stream.py",
        "../trainer/python/tests/check_stream.py",
    ] {
        let path = repo_file(file);
        let text =
            std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        for name in names_used(&text) {
            assert!(
                Section::parse(&name).is_some(),
                "{file} reads section `{name}`, which schemas/src/batch/sections.rs does not list"
            );
            used.push(name);
        }
    }
    assert!(
        used.iter().any(|n| n == "points"),
        "the readers use `points`: {used:?}"
    );
    assert_eq!(
        names_used(
            r#"a = arrays["pairing_uv"]; b = arrays.get(f'l{l}_nbr'); c = arrays[name]; d = batch["images"]"#
        ),
        ["pairing_uv", "l0_nbr", "images"]
    );
}

/// `"name": "<u4",` lines of a table of trainer/python/superflow/sections.py.
fn python_table(text: &str, table: &str) -> Vec<(String, String)> {
    let start = text
        .find(&format!("{table}: dict[str, str] = {{"))
        .unwrap_or_else(|| panic!("sections.py has no {table}"));
    let body = &text[start..];
    let body = &body[body.find('{').unwrap() + 1..body.find('}').unwrap()];
    body.lines()
        .filter_map(|line| {
            let (name, dtype) = line.trim().trim_end_matches(',').split_once(": ")?;
            Some((
                name.trim_matches('"').to_string(),
                dtype.trim_matches('"').to_string(),
            ))
        })
        .filter(|(name, _)| !name.contains(' '))
        .collect()
}

#[test]
fn the_python_package_section_table_is_the_rust_one() {
    let path = repo_file("../trainer/python/superflow/sections.py");
    let text = std::fs::read_to_string(&path).unwrap();
    let spelled = |s: Section| s.spec().dtype.numpy().to_string();
    let batch: Vec<(String, String)> = Section::BATCH
        .iter()
        .map(|s| (s.name().into_owned(), spelled(*s)))
        .collect();
    assert_eq!(python_table(&text, "BATCH_SECTIONS"), batch);
    let level: Vec<(String, String)> = Section::of_level(0)
        .iter()
        .map(|s| (s.name().trim_start_matches("l0_").to_string(), spelled(*s)))
        .collect();
    assert_eq!(python_table(&text, "LEVEL_SECTIONS"), level);
}
