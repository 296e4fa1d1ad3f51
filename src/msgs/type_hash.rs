//! REP-2016 type hashes (`RIHS01_…`) of minflow's messages, computed from the `.msg` files in
//! `msgs/` exactly as ROS 2 Jazzy's `rosidl_generator_type_description` does, so that the
//! `rmw_zenoh` key expressions and liveliness tokens of `--transport ros2-zenoh` carry the
//! hash a C++ `rmw_zenoh` peer expects (`src/transport/ros2/`).
//!
//! The algorithm (rosidl `rosidl_generator_type_description/__init__.py`, `calculate_type_hash`
//! and `extract_full_type_description`): each `.msg` becomes an `IndividualTypeDescription`
//! (type name `pkg/msg/Type`, its fields in order, each with a `FieldType`: `type_id` from
//! `type_description_interfaces/msg/FieldType`, array or bound `capacity`, `string_capacity`,
//! `nested_type_name`); constants, comments and default values are left out. The type's
//! `TypeDescription` adds every type it references, directly or not, sorted by name. The hash is
//! `RIHS01_` + the lowercase hex SHA-256 of that description as Python's
//! `json.dumps(..., ensure_ascii=True, separators=(', ', ': '))` writes it ([`hashable_json`]).
//! `.msg` syntax follows `rosidl_adapter` (which turns `.msg` into IDL first: `char` becomes
//! `uint8`, `byte` becomes `octet`, a message without fields gets
//! `uint8 structure_needs_at_least_one_member`).
//!
//! `tests/python/rihs01.py` computes the same hashes independently from the same files;
//! `tests/it/transport_type_hash.rs` compares the two, checks both against the hashes Jazzy
//! publishes for `std_msgs/msg/Header`, `builtin_interfaces/msg/Time` and `std_msgs/msg/String`,
//! and checks that `--transport ros2-zenoh` puts the hash on the wire.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use sha2::{Digest, Sha256};

use super::status::{STATUS_MSG, STATUS_TYPE_NAME};
use super::{HEADER_MSG, PARTICLE_FRAME_MSG, TIME_MSG, TYPE_NAME};

/// The `.msg` definitions minflow ships (`msgs/`), by full ROS 2 type name: its two messages
/// and the standard types they use.
pub const MSG_DEFINITIONS: [(&str, &str); 4] = [
    (TYPE_NAME, PARTICLE_FRAME_MSG),
    (STATUS_TYPE_NAME, STATUS_MSG),
    ("std_msgs/msg/Header", HEADER_MSG),
    ("builtin_interfaces/msg/Time", TIME_MSG),
];

/// Why a type hash could not be computed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TypeHashError {
    /// A type name that is not `pkg/msg/Type`.
    #[error("{0:?} is not a full ROS 2 message type name (pkg/msg/Type)")]
    TypeName(String),
    /// A line of a `.msg` definition that `rosidl_adapter` would reject too.
    #[error("{type_name}, line {line}: {reason}")]
    Syntax {
        /// The type whose definition it is.
        type_name: String,
        /// 1-based line number.
        line: usize,
        /// What is wrong with it.
        reason: String,
    },
    /// A referenced type with no definition among those given.
    #[error("{type_name} references {missing}, whose definition is not given")]
    MissingDefinition {
        /// The type that references it.
        type_name: String,
        /// The type without a definition.
        missing: String,
    },
}

/// A `type_description_interfaces/msg/Field` as hashed (no `default_value`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FieldDescription {
    /// Field name.
    pub name: String,
    /// `FieldType.type_id`: the base id (1 nested, 2..=22 primitives and strings), plus 48 for a
    /// fixed array, 96 for a bounded sequence, 144 for an unbounded sequence.
    pub type_id: u8,
    /// Fixed array size or sequence bound, else 0.
    pub capacity: u64,
    /// Bound of a `string<=N` / `wstring<=N`, else 0.
    pub string_capacity: u64,
    /// `pkg/msg/Type` of a nested type, else empty.
    pub nested_type_name: String,
}

/// A `type_description_interfaces/msg/IndividualTypeDescription`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IndividualTypeDescription {
    /// `pkg/msg/Type`.
    pub type_name: String,
    /// The fields, in definition order.
    pub fields: Vec<FieldDescription>,
}

/// The RIHS01 hash of one of minflow's own types (a name in [`MSG_DEFINITIONS`], e.g.
/// [`TYPE_NAME`]), from the `.msg` files compiled into the binary.
///
/// # Errors
/// [`TypeHashError::MissingDefinition`] for a type not in [`MSG_DEFINITIONS`].
pub fn minflow_type_hash(type_name: &str) -> Result<String, TypeHashError> {
    rihs01(type_name, &MSG_DEFINITIONS)
}

/// The RIHS01 hash (`RIHS01_` + 64 lowercase hex digits) of `type_name`, given the `.msg`
/// text of it and of every type it references as `(pkg/msg/Type, text)` pairs.
///
/// # Errors
/// See [`hashable_json`].
pub fn rihs01(type_name: &str, definitions: &[(&str, &str)]) -> Result<String, TypeHashError> {
    let digest = Sha256::digest(hashable_json(type_name, definitions)?.as_bytes());
    let mut hash = String::from("RIHS01_");
    for byte in digest {
        let _ = write!(hash, "{byte:02x}");
    }
    Ok(hash)
}

/// The exact text rosidl hashes: `{"type_description": T, "referenced_type_descriptions":
/// [R...]}` with the referenced types sorted by name, in Python `json.dumps` formatting.
///
/// # Errors
/// [`TypeHashError::MissingDefinition`] when `type_name` or a type it references is not in
/// `definitions`; [`TypeHashError::Syntax`] / [`TypeHashError::TypeName`] for a bad definition.
pub fn hashable_json(
    type_name: &str,
    definitions: &[(&str, &str)],
) -> Result<String, TypeHashError> {
    let lookup = |name: &str, user: &str| {
        definitions
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, text)| *text)
            .ok_or_else(|| TypeHashError::MissingDefinition {
                type_name: user.to_owned(),
                missing: name.to_owned(),
            })
    };
    let top = parse_msg(type_name, lookup(type_name, type_name)?)?;
    let mut referenced = BTreeMap::new();
    let mut queue: Vec<(String, String)> = nested_names(&top);
    while let Some((name, user)) = queue.pop() {
        if !referenced.contains_key(&name) {
            let description = parse_msg(&name, lookup(&name, &user)?)?;
            queue.extend(nested_names(&description));
            referenced.insert(name, description);
        }
    }
    let mut json = String::from("{\"type_description\": ");
    write_description(&top, &mut json);
    json.push_str(", \"referenced_type_descriptions\": [");
    for (i, description) in referenced.values().enumerate() {
        if i > 0 {
            json.push_str(", ");
        }
        write_description(description, &mut json);
    }
    json.push_str("]}");
    Ok(json)
}

/// (nested type name, the type that uses it) for each nested field of `description`.
fn nested_names(description: &IndividualTypeDescription) -> Vec<(String, String)> {
    description
        .fields
        .iter()
        .filter(|f| !f.nested_type_name.is_empty())
        .map(|f| (f.nested_type_name.clone(), description.type_name.clone()))
        .collect()
}

/// Parses the `.msg` text of `type_name` (`pkg/msg/Type`) into its description: one field per
/// field line, constants (`TYPE NAME=VALUE`), comments and default values left out.
///
/// # Errors
/// [`TypeHashError::TypeName`] for a bad `type_name`, [`TypeHashError::Syntax`] for a line that
/// is not a field or constant definition.
pub fn parse_msg(type_name: &str, text: &str) -> Result<IndividualTypeDescription, TypeHashError> {
    let package = match type_name.split('/').collect::<Vec<_>>()[..] {
        [pkg, "msg", name] if is_identifier(pkg) && is_identifier(name) => pkg,
        _ => return Err(TypeHashError::TypeName(type_name.to_owned())),
    };
    let mut fields = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let syntax = |reason: String| TypeHashError::Syntax {
            type_name: type_name.to_owned(),
            line: i + 1,
            reason,
        };
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let (type_str, rest) = line
            .split_once(char::is_whitespace)
            .ok_or_else(|| syntax(format!("{line:?} has a type but no name")))?;
        if rest.contains('=') {
            continue; // a constant: not part of the type description
        }
        let name = rest.split_whitespace().next().unwrap_or("");
        if !is_field_name(name) {
            return Err(syntax(format!("{name:?} is not a field name")));
        }
        let mut field = parse_field_type(type_str, package).map_err(syntax)?;
        field.name = name.to_owned();
        fields.push(field);
    }
    if fields.is_empty() {
        // rosidl_adapter gives an empty message this one member.
        fields.push(FieldDescription {
            name: "structure_needs_at_least_one_member".to_owned(),
            type_id: 3, // uint8
            capacity: 0,
            string_capacity: 0,
            nested_type_name: String::new(),
        });
    }
    Ok(IndividualTypeDescription {
        type_name: type_name.to_owned(),
        fields,
    })
}

/// A package or type name: ASCII letters, digits and underscores, not empty.
fn is_identifier(s: &str) -> bool {
    !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
}

/// A ROS 2 field name: a lowercase letter, then lowercase letters, digits and single
/// underscores, not ending in an underscore.
fn is_field_name(name: &str) -> bool {
    name.starts_with(|c: char| c.is_ascii_lowercase())
        && name
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
        && !name.contains("__")
        && !name.ends_with('_')
}

/// `FieldType` of a `.msg` type string (`float32[]`, `string<=8`, `std_msgs/Header`,
/// `int32[<=4]`, `Other` for a type of the same `package`); the name is left empty.
fn parse_field_type(type_str: &str, package: &str) -> Result<FieldDescription, String> {
    let (base, offset, capacity) = match type_str.split_once('[') {
        None => (type_str, 0, 0),
        Some((base, bound)) => {
            let bound = bound
                .strip_suffix(']')
                .ok_or_else(|| format!("{type_str:?}: unclosed array bracket"))?;
            let number = |s: &str| {
                s.parse::<u64>()
                    .ok()
                    .filter(|&n| n > 0)
                    .ok_or_else(|| format!("{type_str:?}: bad array size {s:?}"))
            };
            match bound {
                "" => (base, 144, 0),
                b => match b.strip_prefix("<=") {
                    Some(max) => (base, 96, number(max)?),
                    None => (base, 48, number(b)?),
                },
            }
        }
    };
    let (base_id, string_capacity, nested_type_name) = base_type(base, package)?;
    Ok(FieldDescription {
        name: String::new(),
        type_id: base_id + offset,
        capacity,
        string_capacity,
        nested_type_name,
    })
}

/// (`type_id`, `string_capacity`, `nested_type_name`) of a type without array suffix.
fn base_type(base: &str, package: &str) -> Result<(u8, u64, String), String> {
    let primitive = match base {
        "int8" => Some(2),
        "uint8" | "char" => Some(3),
        "int16" => Some(4),
        "uint16" => Some(5),
        "int32" => Some(6),
        "uint32" => Some(7),
        "int64" => Some(8),
        "uint64" => Some(9),
        "float32" => Some(10),
        "float64" => Some(11),
        "bool" => Some(15),
        "byte" => Some(16),
        "string" => Some(17),
        "wstring" => Some(18),
        _ => None,
    };
    if let Some(id) = primitive {
        return Ok((id, 0, String::new()));
    }
    for (prefix, id) in [("string<=", 21), ("wstring<=", 22)] {
        if let Some(max) = base.strip_prefix(prefix) {
            let max = max
                .parse::<u64>()
                .ok()
                .filter(|&n| n > 0)
                .ok_or_else(|| format!("{base:?}: bad string bound"))?;
            return Ok((id, max, String::new()));
        }
    }
    let (pkg, name) = base.split_once('/').unwrap_or((package, base));
    if !is_identifier(pkg)
        || !is_identifier(name)
        || !name.starts_with(|c: char| c.is_ascii_uppercase())
    {
        return Err(format!("{base:?} is not a primitive or message type"));
    }
    Ok((1, 0, format!("{pkg}/msg/{name}")))
}

/// Appends `description` as rosidl's hashed JSON (field keys in the order of the messages).
fn write_description(description: &IndividualTypeDescription, out: &mut String) {
    out.push_str("{\"type_name\": ");
    write_json_string(&description.type_name, out);
    out.push_str(", \"fields\": [");
    for (i, f) in description.fields.iter().enumerate() {
        if i > 0 {
            out.push_str(", ");
        }
        out.push_str("{\"name\": ");
        write_json_string(&f.name, out);
        let _ = write!(
            out,
            ", \"type\": {{\"type_id\": {}, \"capacity\": {}, \"string_capacity\": {}, \
             \"nested_type_name\": ",
            f.type_id, f.capacity, f.string_capacity
        );
        write_json_string(&f.nested_type_name, out);
        out.push_str("}}");
    }
    out.push_str("]}");
}

/// A JSON string: every name that reaches here is made of ASCII letters, digits, `_` and `/`
/// (checked while parsing), which Python's `json.dumps` writes unescaped.
fn write_json_string(s: &str, out: &mut String) {
    debug_assert!(s
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '/'));
    out.push('"');
    out.push_str(s);
    out.push('"');
}
