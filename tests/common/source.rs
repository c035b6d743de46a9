//! Reading the crate's sources as text, for the tests that check them (tests/layout.rs,
//! tests/allocation_sizes.rs): std only, so that those tests compile on their own
//! (`rustc --edition 2021 --test tests/layout.rs`).

use std::path::{Path, PathBuf};

/// Every `.rs` file below `dir`, sorted, recursively.
pub fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .expect("src/ is readable")
        .map(|e| e.expect("directory entry").path())
        .collect();
    entries.sort();
    for path in entries {
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// Blanks comments, string and char literals (keeping line structure), so that paths
/// in docs and messages are not read as imports.
pub fn strip(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'/' && b.get(i + 1) == Some(&b'/') {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if b[i] == b'/' && b.get(i + 1) == Some(&b'*') {
            let mut depth = 0;
            while i < b.len() {
                if b[i] == b'/' && b.get(i + 1) == Some(&b'*') {
                    depth += 1;
                    i += 2;
                } else if b[i] == b'*' && b.get(i + 1) == Some(&b'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    if b[i] == b'\n' {
                        out.push(b'\n');
                    }
                    i += 1;
                }
            }
        } else if b[i] == b'"' || (b[i] == b'r' && matches!(b.get(i + 1), Some(b'"' | b'#'))) {
            // Plain or raw string: skip to its end.
            if b[i] == b'r' {
                let mut hashes = 0;
                i += 1;
                while b.get(i) == Some(&b'#') {
                    hashes += 1;
                    i += 1;
                }
                if b.get(i) != Some(&b'"') {
                    out.push(b' ');
                    continue;
                }
                i += 1;
                'raw: while i < b.len() {
                    if b[i] == b'"' && (0..hashes).all(|k| b.get(i + 1 + k) == Some(&b'#')) {
                        i += 1 + hashes;
                        break 'raw;
                    }
                    if b[i] == b'\n' {
                        out.push(b'\n');
                    }
                    i += 1;
                }
            } else {
                i += 1;
                while i < b.len() && b[i] != b'"' {
                    if b[i] == b'\\' {
                        i += 1;
                    }
                    if i < b.len() && b[i] == b'\n' {
                        out.push(b'\n');
                    }
                    i += 1;
                }
                i += 1;
            }
            out.push(b' ');
        } else if b[i] == b'\''
            && ((b.get(i + 2) == Some(&b'\'')) || (b.get(i + 1) == Some(&b'\\')))
        {
            // A char literal ('a', '\n', '\u{..}'); lifetimes ('a) are left alone.
            i += 1;
            while i < b.len() && b[i] != b'\'' {
                if b[i] == b'\\' {
                    i += 1;
                }
                i += 1;
            }
            i += 1;
            out.push(b' ');
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// Blanks inline `#[cfg(test)] mod name { … }` blocks: test code is not the layout, and
/// their `super::` means the file's own module.
pub fn without_test_modules(code: &str) -> String {
    let mut out = code.to_string();
    let mut from = 0;
    while let Some(i) = out[from..].find("#[cfg(test)]") {
        let at = from + i;
        let rest = out[at + 12..].trim_start();
        let skipped = out.len() - (at + 12) - rest.len();
        let header = rest.split('{').next().unwrap_or("");
        let is_mod = header.trim_start().starts_with("mod ") && !header.contains(';');
        if !is_mod {
            from = at + 12;
            continue;
        }
        let open = at + 12 + skipped + header.len();
        let mut depth = 0;
        let mut end = out.len();
        for (k, c) in out[open..].char_indices() {
            match c {
                '{' => depth += 1,
                '}' => {
                    depth -= 1;
                    if depth == 0 {
                        end = open + k + 1;
                        break;
                    }
                }
                _ => {}
            }
        }
        let blank: String = out[at..end]
            .chars()
            .map(|c| if c == '\n' { '\n' } else { ' ' })
            .collect();
        out.replace_range(at..end, &blank);
        from = end;
    }
    out
}
