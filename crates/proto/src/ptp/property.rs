//! The DevicePropDesc dataset (ISO 15740 §5.5.3): what a device property
//! is, its current value, and the values it takes, as a range or a list.
//! Tools such as libgphoto2 build their settings (e.g. `shutterspeed`,
//! `iso`) from it. rigd's properties are unsigned 16- or 32-bit integers.

use super::{CodecError, PropCode, Reader};

/// DataType code of a u16 value.
pub const DATATYPE_UINT16: u16 = 0x0004;
/// DataType code of a u32 value.
pub const DATATYPE_UINT32: u16 = 0x0006;

/// The values a property takes (the FormFlag and its form).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PropForm {
    /// FormFlag 0: nothing said.
    None,
    /// FormFlag 1: every step from `min` to `max`.
    Range {
        /// Smallest value.
        min: u32,
        /// Largest value.
        max: u32,
        /// Step between values.
        step: u32,
    },
    /// FormFlag 2: exactly these values.
    Enumeration(Vec<u32>),
}

/// One property's description.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DevicePropDesc {
    /// The property.
    pub code: PropCode,
    /// [`DATATYPE_UINT16`] or [`DATATYPE_UINT32`].
    pub data_type: u16,
    /// GetSet: whether the host may set it.
    pub writable: bool,
    /// The value after a reset.
    pub factory_default: u32,
    /// The value now.
    pub current: u32,
    /// The values it takes.
    pub form: PropForm,
}

impl DevicePropDesc {
    fn put_value(&self, out: &mut Vec<u8>, v: u32) -> Result<(), CodecError> {
        match self.data_type {
            DATATYPE_UINT16 => {
                let v = u16::try_from(v).map_err(|_| CodecError::ValueTooWide(v))?;
                out.extend_from_slice(&v.to_le_bytes());
            }
            _ => out.extend_from_slice(&v.to_le_bytes()),
        }
        Ok(())
    }

    /// The dataset's bytes. A value too wide for a u16 property is refused.
    pub fn encode(&self) -> Result<Vec<u8>, CodecError> {
        let mut o = Vec::new();
        o.extend_from_slice(&self.code.0.to_le_bytes());
        let data_type = if self.data_type == DATATYPE_UINT16 {
            DATATYPE_UINT16
        } else {
            DATATYPE_UINT32
        };
        o.extend_from_slice(&data_type.to_le_bytes());
        o.push(u8::from(self.writable));
        self.put_value(&mut o, self.factory_default)?;
        self.put_value(&mut o, self.current)?;
        match &self.form {
            PropForm::None => o.push(0),
            PropForm::Range { min, max, step } => {
                o.push(1);
                for v in [*min, *max, *step] {
                    self.put_value(&mut o, v)?;
                }
            }
            PropForm::Enumeration(values) => {
                o.push(2);
                let n = u16::try_from(values.len())
                    .map_err(|_| CodecError::TooManyValues(values.len()))?;
                o.extend_from_slice(&n.to_le_bytes());
                for v in values {
                    self.put_value(&mut o, *v)?;
                }
            }
        }
        Ok(o)
    }

    /// Decodes the dataset of a u16 or u32 property; another data type, an
    /// unknown form or trailing bytes are refused.
    pub fn decode(buf: &[u8]) -> Result<DevicePropDesc, CodecError> {
        let mut r = Reader::new(buf);
        let code = PropCode(r.u16()?);
        let data_type = r.u16()?;
        let value = |r: &mut Reader<'_>| -> Result<u32, CodecError> {
            match data_type {
                DATATYPE_UINT16 => r.u16().map(u32::from),
                DATATYPE_UINT32 => r.u32(),
                _ => Err(CodecError::UnknownDataType(data_type)),
            }
        };
        let writable = r.u8()? != 0;
        let factory_default = value(&mut r)?;
        let current = value(&mut r)?;
        let form = match r.u8()? {
            0 => PropForm::None,
            1 => PropForm::Range {
                min: value(&mut r)?,
                max: value(&mut r)?,
                step: value(&mut r)?,
            },
            2 => {
                let n = r.u16()?;
                PropForm::Enumeration((0..n).map(|_| value(&mut r)).collect::<Result<_, _>>()?)
            }
            other => return Err(CodecError::UnknownForm(other)),
        };
        r.finish()?;
        Ok(DevicePropDesc {
            code,
            data_type,
            writable,
            factory_default,
            current,
            form,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn an_exposure_list_has_the_spec_layout() {
        let d = DevicePropDesc {
            code: PropCode::ExposureTime,
            data_type: DATATYPE_UINT32,
            writable: true,
            factory_default: 1000,
            current: 2500,
            form: PropForm::Enumeration(vec![1000, 2500]),
        };
        let b = d.encode().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            b,
            [
                0x0D, 0x50, 0x06, 0x00, 1, 0xE8, 0x03, 0, 0, 0xC4, 0x09, 0, 0, 2, 2, 0, 0xE8, 0x03,
                0, 0, 0xC4, 0x09, 0, 0
            ]
        );
        assert_eq!(DevicePropDesc::decode(&b), Ok(d));
    }

    #[test]
    fn a_u16_property_refuses_a_wide_value() {
        let d = DevicePropDesc {
            code: PropCode::ExposureIndex,
            data_type: DATATYPE_UINT16,
            writable: true,
            factory_default: 100,
            current: 70_000,
            form: PropForm::None,
        };
        assert!(d.encode().is_err());
    }

    proptest! {
        #[test]
        fn descriptions_round_trip(
            wide in any::<bool>(),
            writable in any::<bool>(),
            a in any::<u16>(), b in any::<u16>(), c in any::<u16>(),
            list in proptest::collection::vec(any::<u16>(), 0..20),
            form in 0u8..3,
        ) {
            let form = match form {
                0 => PropForm::None,
                1 => PropForm::Range { min: a.into(), max: b.into(), step: c.into() },
                _ => PropForm::Enumeration(list.into_iter().map(u32::from).collect()),
            };
            let d = DevicePropDesc {
                code: PropCode::ExposureIndex,
                data_type: if wide { DATATYPE_UINT32 } else { DATATYPE_UINT16 },
                writable,
                factory_default: a.into(),
                current: b.into(),
                form,
            };
            let bytes = d.encode().unwrap_or_else(|e| panic!("{e}"));
            prop_assert_eq!(DevicePropDesc::decode(&bytes), Ok(d));
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let _ = DevicePropDesc::decode(&bytes);
        }
    }
}
