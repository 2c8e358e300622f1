//! Reading a JSON document so that a problem names its place: the path of a field of the wrong
//! shape, the path at a syntax error's byte offset (`samples[3].pose.t_mm[1]`, which serde
//! reports only as a line and column), and the path to a NUL character.

use super::Rejection;
use serde::de::DeserializeOwned;

/// Parses a document, naming the field of any problem: text that is not UTF-8 or not JSON is
/// [`Rejection::Malformed`], a well-formed document of the wrong shape names its field (`body`
/// when it is the whole).
pub fn parse<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, Rejection> {
    let text = std::str::from_utf8(bytes)
        .map_err(|e| Rejection::Malformed(format!("the body is not UTF-8: {e}")))?;
    // In JSON a NUL can only be written `\u0000`: look closer only when that is there.
    if text.contains("\\u0000")
        && let Ok(value) = serde_json::from_str::<serde_json::Value>(text)
        && let Some(path) = path_to_nul(&value)
    {
        return Err(Rejection::field(
            path,
            "text may not hold the NUL character (U+0000)",
        ));
    }
    let mut de = serde_json::Deserializer::from_str(text);
    serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        if inner.is_syntax() || inner.is_eof() {
            Rejection::Malformed(format!("malformed JSON: {inner}"))
        } else {
            Rejection::field(if path == "." { "body" } else { &path }, inner.to_string())
        }
    })
}

enum Frame {
    Object {
        key: Option<String>,
        expecting_key: bool,
    },
    Array {
        index: usize,
    },
}

/// The path of the value being read at byte `offset` of `text`.
pub fn path_at(text: &str, offset: usize) -> String {
    let bytes = text.as_bytes();
    let end = offset.min(bytes.len());
    let mut stack: Vec<Frame> = Vec::new();
    let mut i = 0;
    while i < end {
        match bytes[i] {
            b'"' => {
                let start = i + 1;
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' {
                    if bytes[i] == b'\\' {
                        i += 1;
                    }
                    i += 1;
                }
                if let Some(Frame::Object { key, expecting_key }) = stack.last_mut()
                    && *expecting_key
                {
                    *key = Some(
                        String::from_utf8_lossy(&bytes[start..i.min(bytes.len())]).into_owned(),
                    );
                }
            }
            b'{' => stack.push(Frame::Object {
                key: None,
                expecting_key: true,
            }),
            b'[' => stack.push(Frame::Array { index: 0 }),
            b'}' | b']' => {
                stack.pop();
            }
            b':' => {
                if let Some(Frame::Object { expecting_key, .. }) = stack.last_mut() {
                    *expecting_key = false;
                }
            }
            b',' => match stack.last_mut() {
                Some(Frame::Object { key, expecting_key }) => {
                    *key = None;
                    *expecting_key = true;
                }
                Some(Frame::Array { index }) => *index += 1,
                None => {}
            },
            _ => {}
        }
        i += 1;
    }
    let mut path = String::new();
    for frame in &stack {
        match frame {
            Frame::Object { key: Some(k), .. } => {
                if !path.is_empty() {
                    path.push('.');
                }
                path.push_str(k);
            }
            Frame::Object { key: None, .. } => {}
            Frame::Array { index } => path.push_str(&format!("[{index}]")),
        }
    }
    path
}

/// The byte offset of a 1-based line and column (as serde_json reports them).
pub fn offset_of(text: &str, line: usize, column: usize) -> usize {
    let line_start: usize = text
        .split_inclusive('\n')
        .take(line.saturating_sub(1))
        .map(str::len)
        .sum();
    (line_start + column.saturating_sub(1)).min(text.len())
}

/// The index of the item in a `{"samples": [...]}` batch that a path names, if any.
pub fn item_index(path: &str, array_key: &str) -> Option<usize> {
    let rest = path.strip_prefix(array_key)?.strip_prefix('[')?;
    rest.split(']').next()?.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn path_names_the_item_and_field_of_an_offset() {
        let text = r#"{"samples": [{"link": "A", "pose": {"t_mm": [1, 2, 3]}}, {"link": "B", "pose": {"t_mm": [1, NaN, 3]}}]}"#;
        let offset = text.find("NaN").unwrap();
        let path = path_at(text, offset);
        assert_eq!(path, "samples[1].pose.t_mm[1]");
        assert_eq!(item_index(&path, "samples"), Some(1));
    }

    #[test]
    fn strings_with_brackets_and_escapes_do_not_confuse_the_scan() {
        let text = r#"{"a": "x[{\"", "b": [0, {"c": ]}"#;
        assert_eq!(path_at(text, text.rfind(']').unwrap()), "b[1].c");
    }

    #[test]
    fn offsets_come_from_lines_and_columns() {
        assert_eq!(offset_of("ab\ncd\nef", 3, 2), 7);
    }
}

/// The path of the first string (or object key) in `value` that holds a NUL character
/// (`samples[3].link`; `body` for the value itself).
pub fn path_to_nul(value: &serde_json::Value) -> Option<String> {
    fn walk(value: &serde_json::Value, path: &mut String) -> bool {
        match value {
            serde_json::Value::String(s) => s.contains('\0'),
            serde_json::Value::Array(items) => items.iter().enumerate().any(|(i, item)| {
                let len = path.len();
                path.push_str(&format!("[{i}]"));
                let found = walk(item, path);
                if !found {
                    path.truncate(len);
                }
                found
            }),
            serde_json::Value::Object(map) => map.iter().any(|(key, item)| {
                let len = path.len();
                if !path.is_empty() {
                    path.push('.');
                }
                path.push_str(&key.replace('\0', "\\u0000"));
                let found = key.contains('\0') || walk(item, path);
                if !found {
                    path.truncate(len);
                }
                found
            }),
            _ => false,
        }
    }
    let mut path = String::new();
    walk(value, &mut path).then(|| {
        if path.is_empty() {
            "body".to_owned()
        } else {
            path
        }
    })
}

#[cfg(test)]
mod nul_tests {
    use super::path_to_nul;
    use serde_json::json;

    #[test]
    fn the_path_to_a_nul_names_the_field_and_item() {
        assert_eq!(
            path_to_nul(&json!({"by": "ok", "note": "a\u{0}b"})),
            Some("note".into())
        );
        assert_eq!(
            path_to_nul(&json!({"samples": [{"link": "x"}, {"link": "\u{0}"}]})),
            Some("samples[1].link".into())
        );
        assert_eq!(path_to_nul(&json!("\u{0}")), Some("body".into()));
        assert_eq!(
            path_to_nul(&json!({"by": "a\\u0000b"})),
            None,
            "a written escape"
        );
    }
}
