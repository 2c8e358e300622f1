//! Vocabularies: the closed sets of words the service writes and reads (statuses, kinds, levels,
//! units, codes), each an enum declared once with [`crate::words!`], its words beside its variants.
//!
//! The macro gives every vocabulary the same surface: `ALL` (every value, in the documented
//! order), `name` (its word), `parse` (the value of a word), `Display`, and serde by the word,
//! so a response field, a stored column and a configuration key use one spelling and cannot hold
//! anything else. The HTTP adapter documents each vocabulary's words in the OpenAPI document
//! from `ALL`, and a test checks the vocabulary table of `docs/interface.md` against them.

/// A vocabulary made by [`crate::words!`]: its words, for code generic over vocabularies.
pub trait Word: Copy + Eq + Sized + 'static {
    /// What the vocabulary is, for messages ("alarm level").
    const WHAT: &'static str;
    /// Every value, in the documented order.
    const ALL: &'static [Self];
    /// The value's word.
    fn word(self) -> &'static str;
    /// Every word, in the documented order.
    fn words() -> Vec<&'static str> {
        Self::ALL.iter().map(|w| w.word()).collect()
    }
}

/// Declares a vocabulary: an enum whose variants each name their word.
///
/// ```
/// brokenray::words! {
///     /// A colour.
///     pub enum Colour("colour") {
///         /// Red.
///         Red = "red",
///         /// Dark blue.
///         DarkBlue = "dark_blue",
///     }
/// }
/// assert_eq!(Colour::DarkBlue.name(), "dark_blue");
/// assert_eq!(Colour::parse("red"), Some(Colour::Red));
/// assert_eq!(serde_json::to_string(&Colour::Red).unwrap(), "\"red\"");
/// ```
#[macro_export]
macro_rules! words {
    (
        $(#[$meta:meta])*
        $vis:vis enum $name:ident($what:literal) {
            $( $(#[$vmeta:meta])* $variant:ident = $word:literal ),+ $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        $vis enum $name {
            $( $(#[$vmeta])* $variant ),+
        }

        impl $name {
            /// Every value, in the documented order.
            $vis const ALL: &'static [$name] = &[$($name::$variant),+];
            /// Every word, in the documented order.
            $vis const WORDS: &'static [&'static str] = &[$($word),+];

            /// The word on the wire, in the database and in the configuration.
            $vis fn name(self) -> &'static str {
                match self {
                    $( $name::$variant => $word ),+
                }
            }

            /// The value of a word; `None` for any other text.
            $vis fn parse(word: &str) -> Option<Self> {
                match word {
                    $( $word => Some($name::$variant), )+
                    _ => None,
                }
            }
        }

        impl $crate::words::Word for $name {
            const WHAT: &'static str = $what;
            const ALL: &'static [Self] = $name::ALL;
            fn word(self) -> &'static str {
                self.name()
            }
        }

        impl ::std::fmt::Display for $name {
            fn fmt(&self, f: &mut ::std::fmt::Formatter<'_>) -> ::std::fmt::Result {
                f.write_str(self.name())
            }
        }

        impl ::serde::Serialize for $name {
            fn serialize<S: ::serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                s.serialize_str(self.name())
            }
        }

        impl<'de> ::serde::Deserialize<'de> for $name {
            fn deserialize<D: ::serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                let text = <::std::borrow::Cow<'de, str> as ::serde::Deserialize>::deserialize(d)?;
                $name::parse(&text)
                    .ok_or_else(|| ::serde::de::Error::unknown_variant(&text, $name::WORDS))
            }
        }
    };
}

/// A word of vocabulary `T` read from another program (a site of another version): a word this
/// version does not know is kept as it came, so one new word does not refuse a whole message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Lenient<T> {
    /// A word of the vocabulary.
    Known(T),
    /// Another word.
    Unknown(String),
}

impl<T: Word> Lenient<T> {
    /// The value, when the word is the vocabulary's.
    pub fn known(&self) -> Option<T> {
        match self {
            Lenient::Known(v) => Some(*v),
            Lenient::Unknown(_) => None,
        }
    }

    /// The word as it came.
    pub fn as_str(&self) -> &str {
        match self {
            Lenient::Known(v) => v.word(),
            Lenient::Unknown(w) => w,
        }
    }
}

impl<T: Word> From<T> for Lenient<T> {
    fn from(v: T) -> Self {
        Lenient::Known(v)
    }
}

impl<T: Word> serde::Serialize for Lenient<T> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.as_str())
    }
}

impl<'de, T: Word> serde::Deserialize<'de> for Lenient<T> {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let text = <std::borrow::Cow<'de, str> as serde::Deserialize>::deserialize(d)?;
        Ok(T::ALL.iter().find(|v| v.word() == text).map_or_else(
            || Lenient::Unknown(text.into_owned()),
            |v| Lenient::Known(*v),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::{Lenient, Word};

    crate::words! {
        /// A test vocabulary.
        enum Sample("sample") {
            /// One.
            One = "one",
            /// Two words.
            TwoWords = "two_words",
        }
    }

    #[test]
    fn a_vocabulary_round_trips_through_its_words_and_serde() {
        for &w in Sample::ALL {
            assert_eq!(Sample::parse(w.name()), Some(w));
            let json = serde_json::to_string(&w).unwrap();
            assert_eq!(json, format!("\"{}\"", w.name()));
            assert_eq!(serde_json::from_str::<Sample>(&json).unwrap(), w);
        }
        assert_eq!(Sample::words(), ["one", "two_words"]);
        assert_eq!(Sample::parse("One"), None);
        let err = serde_json::from_str::<Sample>("\"three\"")
            .unwrap_err()
            .to_string();
        assert!(err.contains("three") && err.contains("two_words"), "{err}");
        assert_eq!(<Sample as Word>::WHAT, "sample");
    }

    #[test]
    fn a_lenient_word_keeps_one_it_does_not_know() {
        let known: Lenient<Sample> = serde_json::from_str("\"two_words\"").unwrap();
        assert_eq!(known, Lenient::Known(Sample::TwoWords));
        assert_eq!(known.known(), Some(Sample::TwoWords));
        let other: Lenient<Sample> = serde_json::from_str("\"three\"").unwrap();
        assert_eq!(other.known(), None);
        assert_eq!(other.as_str(), "three");
        // Written back as it came.
        assert_eq!(serde_json::to_string(&other).unwrap(), "\"three\"");
        assert_eq!(serde_json::to_string(&known).unwrap(), "\"two_words\"");
        assert!(serde_json::from_str::<Lenient<Sample>>("3").is_err());
    }
}
