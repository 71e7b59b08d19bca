//! Integers in JSON as JSON Schema counts them: `2304` and `2304.0` are the same integer, so an
//! API whose description says "integer" takes both. serde's own integer types refuse `2304.0`;
//! these take it, and still refuse `2304.5`, a string, or a value out of the type's range,
//! naming the value. For `#[serde(deserialize_with = ...)]` on request fields.

use serde::de::{self, Deserializer, Visitor};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::marker::PhantomData;

/// An integer of type `T` that may come written as an integral float.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(transparent)]
pub struct Integer<T>(pub T);

struct IntegerVisitor<T>(PhantomData<T>);

impl<T: TryFrom<i128>> IntegerVisitor<T> {
    fn fit<E: de::Error>(value: i128) -> Result<T, E> {
        T::try_from(value).map_err(|_| {
            E::custom(format!(
                "{value} is out of range for {}",
                std::any::type_name::<T>()
            ))
        })
    }
}

impl<T: TryFrom<i128>> Visitor<'_> for IntegerVisitor<T> {
    type Value = T;

    fn expecting(&self, formatter: &mut fmt::Formatter) -> fmt::Result {
        formatter.write_str("an integer")
    }

    fn visit_i64<E: de::Error>(self, value: i64) -> Result<T, E> {
        Self::fit(i128::from(value))
    }

    fn visit_u64<E: de::Error>(self, value: u64) -> Result<T, E> {
        Self::fit(i128::from(value))
    }

    fn visit_f64<E: de::Error>(self, value: f64) -> Result<T, E> {
        // Every integral f64 within ±2^127 converts to i128 exactly.
        if value.is_finite() && value.fract() == 0.0 && value.abs() < 1.7e38 {
            Self::fit(value as i128)
        } else {
            Err(E::custom(format!("{value} is not an integer")))
        }
    }
}

impl<'de, T: TryFrom<i128>> Deserialize<'de> for Integer<T> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        deserializer
            .deserialize_any(IntegerVisitor(PhantomData))
            .map(Integer)
    }
}

/// `deserialize_with` for an integer field.
pub fn integer<'de, D: Deserializer<'de>, T: TryFrom<i128>>(
    deserializer: D,
) -> Result<T, D::Error> {
    Integer::deserialize(deserializer).map(|Integer(value)| value)
}

/// `deserialize_with` for an optional integer field (with `#[serde(default)]`).
pub fn optional_integer<'de, D: Deserializer<'de>, T: TryFrom<i128>>(
    deserializer: D,
) -> Result<Option<T>, D::Error> {
    Option::<Integer<T>>::deserialize(deserializer).map(|value| value.map(|Integer(v)| v))
}

/// `deserialize_with` for an optional list of integers (with `#[serde(default)]`).
pub fn optional_integers<'de, D: Deserializer<'de>, T: TryFrom<i128>>(
    deserializer: D,
) -> Result<Option<Vec<T>>, D::Error> {
    Option::<Vec<Integer<T>>>::deserialize(deserializer)
        .map(|list| list.map(|list| list.into_iter().map(|Integer(v)| v).collect()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read<T: TryFrom<i128>>(json: &str) -> Result<T, String> {
        serde_json::from_str::<Integer<T>>(json)
            .map(|Integer(value)| value)
            .map_err(|e| e.to_string())
    }

    #[test]
    fn integral_floats_are_integers_and_nothing_else_is() {
        assert_eq!(read::<u64>("2304"), Ok(2304));
        assert_eq!(read::<u64>("2304.0"), Ok(2304));
        assert_eq!(read::<i64>("-7.0"), Ok(-7));
        assert_eq!(read::<u64>("18446744073709551615"), Ok(u64::MAX));
        assert_eq!(read::<u64>("1e3"), Ok(1000));
        assert!(
            read::<u64>("2304.5")
                .unwrap_err()
                .contains("2304.5 is not an integer")
        );
        assert!(read::<u64>("-1").unwrap_err().contains("out of range"));
        assert!(
            read::<u32>("4294967296")
                .unwrap_err()
                .contains("out of range")
        );
        assert!(read::<u64>("1e300").unwrap_err().contains("not an integer"));
        assert!(read::<u64>("\"7\"").unwrap_err().contains("an integer"));
    }

    #[test]
    fn optional_and_listed_integers() {
        #[derive(Deserialize)]
        struct Body {
            #[serde(default, deserialize_with = "optional_integer")]
            seed: Option<u64>,
            #[serde(default, deserialize_with = "optional_integers")]
            ids: Option<Vec<i64>>,
        }
        let body: Body = serde_json::from_str(r#"{"seed": 5.0, "ids": [1, 2.0]}"#).unwrap();
        assert_eq!((body.seed, body.ids), (Some(5), Some(vec![1, 2])));
        let body: Body = serde_json::from_str(r#"{"seed": null}"#).unwrap();
        assert_eq!((body.seed, body.ids), (None, None));
    }
}
