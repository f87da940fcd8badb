//! A lint over the trainer's sources: burn's ops over the row dimension are called only
//! in `src/rows.rs`.
//!
//! burn 0.22.1's reductions over rows (and so the backward of every broadcast over rows:
//! a `Linear`'s bias, `BatchNorm`) and its scatter-add (the backward of a row gather) are
//! silently wrong on wgpu past the adapter's workgroup limit (65 535 on llvmpipe and
//! several real drivers). `RowOps` runs them in pieces there; a direct call elsewhere
//! trains with wrong gradients on such a device and is right on the CPU, so no numeric
//! test on flex notices it. This test reads `src/` and names every such call outside
//! `rows.rs`, with the `RowOps` method to use instead.
//!
//! A use whose row count is bounded, or that never runs a backward pass, is allowed
//! below with its reason and its exact number of occurrences: a new occurrence in the
//! same file fails until it is looked at.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Calls that reduce or broadcast over rows, gather or scatter rows, with what to call
/// instead.
const ROW_OPS: &[(&str, &str)] = &[
    (".sum_dim(0)", "RowOps::sum_rows"),
    (".mean_dim(0)", "RowOps::sum_rows (then divide)"),
    (".select(0,", "RowOps::gather"),
    (".select_assign(", "RowOps::scatter_add"),
    (".gather(0,", "RowOps::gather"),
    (".scatter(0,", "RowOps::scatter_add"),
    (".expand(", "RowOps::broadcast_rows"),
    (".repeat_dim(0,", "RowOps::broadcast_rows"),
    ("module::linear(", "RowOps::linear"),
    ("module::batch_norm(", "RowOps::batch_norm"),
];

/// burn modules whose `forward` sums or broadcasts over rows, with the `RowOps` method
/// that replaces it. Fields and variables of these types are found by their
/// declarations (`name: Linear`, `let name = LinearConfig::…`).
const ROW_MODULES: &[(&str, &str)] = &[
    ("Linear", "RowOps::linear"),
    ("BatchNorm", "RowOps::batch_norm"),
];

/// Allowed uses: (file under `src/`, the call as reported, occurrences, why).
const ALLOWED: &[(&str, &str, usize, &str)] = &[
    (
        "vit/blocks.rs",
        "qkv.forward(",
        1,
        "the ViT is frozen: it runs on the plain device (no autodiff), so no backward \
         sums over its rows; a forward bias broadcast is element-wise",
    ),
    ("vit/blocks.rs", "proj.forward(", 1, "frozen ViT (above)"),
    ("vit/blocks.rs", "fc1.forward(", 1, "frozen ViT (above)"),
    ("vit/blocks.rs", "fc2.forward(", 1, "frozen ViT (above)"),
    (
        "vit/network.rs",
        "patch_embed.forward(",
        1,
        "frozen ViT (above)",
    ),
    (
        "vit/network.rs",
        ".repeat_dim(0,",
        1,
        "the class token repeated once per image (a few hundred at most), frozen ViT",
    ),
    (
        "sync.rs",
        "a.forward(",
        1,
        "a unit test's model on a 2-row input on the CPU",
    ),
];

/// The `.rs` files under `dir`, recursively.
fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("src/ is readable") {
        let path = entry.expect("a directory entry").path();
        if path.is_dir() {
            sources(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// `source` without comments and with string and character literals emptied, whitespace
/// runs collapsed to one space and removed next to punctuation: `self.qkv\n    .forward(x)`
/// reads `self.qkv.forward(x)`.
fn normalize(source: &str) -> String {
    let chars: Vec<char> = source.chars().collect();
    let at = |i: usize| chars.get(i).copied();
    let mut code = String::with_capacity(source.len());
    let mut i = 0;
    while let Some(c) = at(i) {
        match (c, at(i + 1)) {
            ('/', Some('/')) => {
                while at(i).is_some_and(|c| c != '\n') {
                    i += 1;
                }
            }
            ('/', Some('*')) => {
                let mut depth = 0usize;
                while let Some(c) = at(i) {
                    match (c, at(i + 1)) {
                        ('/', Some('*')) => {
                            depth += 1;
                            i += 2;
                        }
                        ('*', Some('/')) => {
                            depth -= 1;
                            i += 2;
                            if depth == 0 {
                                break;
                            }
                        }
                        _ => i += 1,
                    }
                }
                code.push(' ');
            }
            ('"', _) => {
                i += 1;
                while let Some(c) = at(i) {
                    i += if c == '\\' { 2 } else { 1 };
                    if c == '"' {
                        break;
                    }
                }
                code.push_str("\"\"");
            }
            // Character literals ('"', '\''); a lifetime ('a) stays.
            ('\'', Some('\\')) => {
                i += 3;
                while at(i).is_some_and(|c| c != '\'') {
                    i += 1;
                }
                i += 1;
                code.push_str("' '");
            }
            ('\'', Some(_)) if at(i + 2) == Some('\'') => {
                i += 3;
                code.push_str("' '");
            }
            (c, _) => {
                code.push(c);
                i += 1;
            }
        }
    }
    let mut out = String::with_capacity(code.len());
    let mut space = false;
    for c in code.chars() {
        if c.is_whitespace() {
            space = true;
            continue;
        }
        if space && out.chars().last().is_some_and(is_word) && is_word(c) {
            out.push(' ');
        }
        space = false;
        out.push(c);
    }
    out
}

fn is_word(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// The identifier that ends just before byte `end` of `code`.
fn word_before(code: &str, end: usize) -> &str {
    let start = code[..end]
        .char_indices()
        .rev()
        .find(|&(_, c)| !is_word(c))
        .map_or(0, |(i, c)| i + c.len_utf8());
    &code[start..end]
}

/// Names declared with type `module` in `code`: `name: Module`, `name: &burn::nn::Module`
/// (fields, parameters, typed `let`s) and `let name = ModuleConfig::…`.
fn declared(code: &str, module: &str) -> Vec<String> {
    let mut names = Vec::new();
    for (at, _) in code.match_indices(module) {
        let before = code[..at].chars().last();
        let after = code[at + module.len()..].chars().next();
        if before.is_some_and(is_word) || after.is_some_and(is_word) {
            continue;
        }
        // Back over a path (`burn::nn::`) and a reference.
        let mut p = at;
        while code[..p].ends_with("::") {
            let segment = word_before(code, p - 2);
            if segment.is_empty() {
                break;
            }
            p -= 2 + segment.len();
        }
        if code[..p].ends_with('&') {
            p -= 1;
        }
        if code[..p].ends_with(':') && !code[..p].ends_with("::") {
            names.push(word_before(code, p - 1).to_string());
        }
    }
    let built = format!("={module}Config::");
    for (at, _) in code.match_indices(&built) {
        names.push(word_before(code, at).to_string());
    }
    names.retain(|n| !n.is_empty() && !n.starts_with(|c: char| c.is_ascii_digit()));
    names
}

/// Every row op call in `code`: (the call as reported, what to use instead).
fn row_op_calls(code: &str, modules: &[(String, &'static str)]) -> Vec<(String, &'static str)> {
    let mut found = Vec::new();
    for &(call, instead) in ROW_OPS {
        for _ in code.match_indices(call) {
            found.push((call.to_string(), instead));
        }
    }
    for (name, instead) in modules {
        let call = format!("{name}.forward(");
        for (at, _) in code.match_indices(&call) {
            let before = code[..at].chars().last();
            if !before.is_some_and(is_word) {
                found.push((call.clone(), *instead));
            }
        }
    }
    found
}

#[test]
fn burn_ops_over_rows_are_called_only_in_rows_rs() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    sources(&src, &mut files);
    files.sort();
    let codes: Vec<(String, String)> = files
        .iter()
        .map(|path| {
            let rel = path
                .strip_prefix(&src)
                .expect("under src/")
                .to_string_lossy()
                .replace('\\', "/");
            let source = std::fs::read_to_string(path).expect("a readable source file");
            (rel, normalize(&source))
        })
        .filter(|(rel, _)| rel != "rows.rs")
        .collect();
    // Module fields are declared in one file and may be called in another.
    let mut modules: Vec<(String, &'static str)> = Vec::new();
    for (_, code) in &codes {
        for &(module, instead) in ROW_MODULES {
            for name in declared(code, module) {
                if !modules.iter().any(|(n, _)| *n == name) {
                    modules.push((name, instead));
                }
            }
        }
    }
    assert!(
        modules.iter().any(|(n, _)| n == "head") && modules.iter().any(|(n, _)| n == "bn1"),
        "the lint no longer finds the UNet's Linear and BatchNorm fields: {modules:?}"
    );

    let mut counts: BTreeMap<(String, String), (usize, &'static str)> = BTreeMap::new();
    for (rel, code) in &codes {
        for (call, instead) in row_op_calls(code, &modules) {
            counts.entry((rel.clone(), call)).or_insert((0, instead)).0 += 1;
        }
    }
    let mut problems = Vec::new();
    for ((file, call), (count, instead)) in &counts {
        match ALLOWED.iter().find(|(f, c, ..)| f == file && c == call) {
            Some(&(_, _, allowed, _)) if allowed == *count => {}
            Some(&(_, _, allowed, _)) => problems.push(format!(
                "src/{file}: `{call}` {count}× (allowed {allowed}×): use {instead}, or look at \
                 the new use and update the allowance"
            )),
            None => problems.push(format!(
                "src/{file}: `{call}` {count}×: burn's op over rows, wrong on wgpu past the \
                 workgroup limit; use {instead}"
            )),
        }
    }
    for (file, call, ..) in ALLOWED {
        if !counts.contains_key(&(file.to_string(), call.to_string())) {
            problems.push(format!(
                "src/{file}: `{call}` is allowed but no longer used: remove the allowance"
            ));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_lint_sees_through_layout_and_comments() {
    let code = normalize(
        "struct H {\n    conv: Linear, // conv.forward( in a comment\n    bn: burn::nn::BatchNorm,\n}\n\
         /* x.sum_dim(0) */ let s = \"a.sum_dim(0) // text\";\n\
         let y = self\n    .conv\n    .forward(x);\n let z = x\n    .sum_dim( 0 );\n\
         let mut lin = LinearConfig::new(2, 2).init(&d); lin.forward(x); reconv.forward(x);\n\
         let c = '\"'; let t = x.select(0, i);",
    );
    let mut modules: Vec<(String, &'static str)> = Vec::new();
    for &(module, instead) in ROW_MODULES {
        modules.extend(declared(&code, module).into_iter().map(|n| (n, instead)));
    }
    let names: Vec<&str> = modules.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["conv", "lin", "bn"], "{code}");
    let calls: Vec<String> = row_op_calls(&code, &modules)
        .into_iter()
        .map(|(c, _)| c)
        .collect();
    // Not in comments, strings or around a character literal.
    assert_eq!(
        calls,
        [".sum_dim(0)", ".select(0,", "conv.forward(", "lin.forward("],
        "{code}"
    );
}
