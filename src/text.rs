//! Numbers as text both ways without `core`'s float machinery, and a fixed-size buffer to write lines into.
//!
//! `core`'s float formatting (shortest round trip) and parsing (correctly rounded, with its 10 KiB table of powers
//! of five) cost more flash than the firmware can spare. [`Num`] writes a number with a given count of significant
//! digits, and [`parse_decimal`] reads one, both by scaling in f64: within a few units in the last place, enough for
//! every quantity this firmware reports or accepts (volts, hertz, sample counts).

use core::fmt;

/// `x` with at most `digits` significant digits (1 to 17), trailing zeros dropped: plain notation between 1e-3 and
/// 1e6, scientific (`1.2345e8`) outside. `nan`, `inf`, `-inf` as such.
#[derive(Clone, Copy, Debug)]
pub struct Num(pub f64, pub u8);

impl fmt::Display for Num {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let Num(x, digits) = *self;
        let digits = digits.clamp(1, 17) as u32;
        if x.is_nan() {
            return f.write_str("nan");
        }
        if x.is_sign_negative() && x != 0.0 {
            f.write_str("-")?;
        }
        let a = libm::fabs(x);
        if a.is_infinite() {
            return f.write_str("inf");
        }
        if a == 0.0 {
            return f.write_str("0");
        }
        // a = m 10^e with m in [1, 10).
        let (mut m, mut e) = (a, 0i32);
        while m >= 1e16 {
            m /= 1e16;
            e += 16;
        }
        while m >= 10.0 {
            m /= 10.0;
            e += 1;
        }
        while m < 1e-16 {
            m *= 1e16;
            e -= 16;
        }
        while m < 1.0 {
            m *= 10.0;
            e -= 1;
        }
        let unit = 10u64.pow(digits - 1);
        let mut n = libm::round(m * unit as f64) as u64;
        if n >= 10 * unit {
            n /= 10;
            e += 1;
        }
        // The digits of n, most significant first, trailing zeros dropped.
        let mut buf = [0u8; 17];
        for i in (0..digits as usize).rev() {
            buf[i] = b'0' + (n % 10) as u8;
            n /= 10;
        }
        let mut len = digits as usize;
        while len > 1 && buf[len - 1] == b'0' {
            len -= 1;
        }
        let digits = &buf[..len];
        fn text(b: &[u8]) -> &str {
            core::str::from_utf8(b).unwrap_or("?")
        }
        if (-3..6).contains(&e) {
            if e < 0 {
                f.write_str("0.")?;
                for _ in 0..(-e - 1) {
                    f.write_str("0")?;
                }
                f.write_str(text(digits))
            } else {
                let int = e as usize + 1;
                if len <= int {
                    f.write_str(text(digits))?;
                    for _ in len..int {
                        f.write_str("0")?;
                    }
                    Ok(())
                } else {
                    f.write_str(text(&digits[..int]))?;
                    f.write_str(".")?;
                    f.write_str(text(&digits[int..]))
                }
            }
        } else {
            f.write_str(text(&digits[..1]))?;
            if len > 1 {
                f.write_str(".")?;
                f.write_str(text(&digits[1..]))?;
            }
            write!(f, "e{e}")
        }
    }
}

/// A decimal number: `[+-]digits[.digits][(e|E)[+-]digits]` (at least one digit before or after the point). `None`
/// for anything else, including `nan` and `inf`. Within a few ulps of the correctly rounded value (within a few
/// ulps of `f64::MAX` it may overflow to infinity, which callers refuse as not finite).
pub fn parse_decimal(s: &str) -> Option<f64> {
    let b = s.as_bytes();
    let mut i = 0;
    let negative = match b.first() {
        Some(b'-') => {
            i += 1;
            true
        }
        Some(b'+') => {
            i += 1;
            false
        }
        _ => false,
    };
    // Up to 19 significant digits in a u64; further digits only shift the exponent.
    let (mut mantissa, mut exp10, mut digits) = (0u64, 0i32, 0u32);
    let mut digit = |c: u8, after_point: bool, exp10: &mut i32| {
        if mantissa < 1_000_000_000_000_000_000 {
            mantissa = mantissa * 10 + (c - b'0') as u64;
            *exp10 -= after_point as i32;
        } else {
            *exp10 += !after_point as i32;
        }
        digits += 1;
    };
    while i < b.len() && b[i].is_ascii_digit() {
        digit(b[i], false, &mut exp10);
        i += 1;
    }
    if i < b.len() && b[i] == b'.' {
        i += 1;
        while i < b.len() && b[i].is_ascii_digit() {
            digit(b[i], true, &mut exp10);
            i += 1;
        }
    }
    if digits == 0 {
        return None;
    }
    if i < b.len() && (b[i] == b'e' || b[i] == b'E') {
        i += 1;
        let sign = match b.get(i) {
            Some(b'-') => {
                i += 1;
                -1
            }
            Some(b'+') => {
                i += 1;
                1
            }
            _ => 1,
        };
        let start = i;
        let mut e = 0i32;
        while i < b.len() && b[i].is_ascii_digit() {
            e = (e * 10 + (b[i] - b'0') as i32).min(10_000);
            i += 1;
        }
        if i == start {
            return None;
        }
        exp10 += sign * e;
    }
    if i != b.len() {
        return None;
    }
    let mut x = mantissa as f64;
    let (mut e, up) = (exp10.unsigned_abs(), exp10 > 0);
    // Powers of ten by squaring: exact up to 1e22, then within an ulp or two per step.
    let mut p = 10.0f64;
    while e > 0 && x != 0.0 && x.is_finite() {
        if e & 1 == 1 {
            x = if up { x * p } else { x / p };
        }
        p *= p;
        e >>= 1;
    }
    Some(if negative { -x } else { x })
}

/// A fixed buffer that `write!` fills; what does not fit is cut and the buffer remembers it (ending in `...\n`, which
/// takes the end of what was written when less room is left: a cut reply still ends its line).
#[derive(Clone, Debug)]
pub struct TextBuf<const N: usize> {
    buf: [u8; N],
    len: usize,
    truncated: bool,
}

impl<const N: usize> Default for TextBuf<N> {
    fn default() -> Self {
        TextBuf { buf: [0; N], len: 0, truncated: false }
    }
}

impl<const N: usize> TextBuf<N> {
    /// The bytes written.
    pub fn as_bytes(&self) -> &[u8] {
        &self.buf[..self.len]
    }
    /// As text.
    pub fn as_str(&self) -> &str {
        core::str::from_utf8(self.as_bytes()).unwrap_or("")
    }
    /// Empty it.
    pub fn clear(&mut self) {
        self.len = 0;
        self.truncated = false;
    }
    /// Whether something was cut.
    pub fn truncated(&self) -> bool {
        self.truncated
    }
}

impl<const N: usize> fmt::Write for TextBuf<N> {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        let room = N - self.len;
        if s.len() <= room && !self.truncated {
            self.buf[self.len..self.len + s.len()].copy_from_slice(s.as_bytes());
            self.len += s.len();
            return Ok(());
        }
        if !self.truncated {
            // Cut at a character boundary, leaving room for the marker and the line end: with less room left than
            // they take, they take the end of what was written before (a cut reply still ends its line).
            let limit = N.saturating_sub(4);
            let mut cut = limit.saturating_sub(self.len).min(s.len());
            if self.len > limit {
                // Back to the start of the character `limit` falls in, as the cut of `s` below.
                let written = self.as_str();
                let mut end = limit;
                while !written.is_char_boundary(end) {
                    end -= 1;
                }
                self.len = end;
            }
            while !s.is_char_boundary(cut) {
                cut -= 1;
            }
            self.buf[self.len..self.len + cut].copy_from_slice(&s.as_bytes()[..cut]);
            self.len += cut;
            for &b in b"...\n" {
                if self.len < N {
                    self.buf[self.len] = b;
                    self.len += 1;
                }
            }
            self.truncated = true;
        }
        Err(fmt::Error)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::format;

    #[test]
    fn numbers_read_as_expected() {
        let cases: [(f64, u8, &str); 18] = [
            (0.0, 6, "0"),
            (1.0, 6, "1"),
            (-2.5, 6, "-2.5"),
            (1053.2149, 6, "1053.21"),
            (999_999.7, 6, "1e6"),
            (123_456.0, 6, "123456"),
            (1.342_553_6e8, 6, "1.34255e8"),
            (0.012_345_67, 6, "0.0123457"),
            (0.000_999_99, 3, "0.001"),
            (2.5e-7, 6, "2.5e-7"),
            (0.0048828125, 15, "0.0048828125"),
            (0.00152587890625, 15, "0.00152587890625"),
            (-50.0, 15, "-50"),
            (10_000.0, 15, "10000"),
            (f64::NAN, 6, "nan"),
            (f64::NEG_INFINITY, 6, "-inf"),
            (1e-300, 3, "1e-300"),
            (1.7976931348623157e308, 4, "1.798e308"),
        ];
        for (x, d, want) in cases {
            assert_eq!(format!("{}", Num(x, d)), want, "{x:e}");
        }
        // Round trip at 15 digits over many magnitudes.
        for k in -20..20 {
            let x = 1.234_567_890_123_4 * 10f64.powi(k);
            let back: f64 = format!("{}", Num(x, 15)).parse().unwrap();
            assert!(((back - x) / x).abs() < 1e-14, "{x:e} {back:e}");
        }
    }

    #[test]
    fn decimals_parse_like_std_within_a_few_ulps() {
        let good = [
            "0",
            "1",
            "-2.5",
            "+3",
            ".5",
            "5.",
            "4.2e2",
            "1E-3",
            "1e+3",
            "-2.5E+02",
            "-0.000125",
            "1000",
            "123456789.123456789",
            "1e300",
            "1e-300",
            "0.1",
            "2.5e-1",
            "99999999999999999999999",
            "7e22",
            "1.5e307",
        ];
        for t in good {
            let want: f64 = t.parse().unwrap();
            let got = parse_decimal(t).unwrap_or_else(|| panic!("{t}"));
            assert!((got - want).abs() <= 4.0 * f64::EPSILON * want.abs(), "{t}: {got:e} vs {want:e}");
        }
        for t in ["", "-", ".", "e5", "1e", "1e+", "nan", "inf", "1.2.3", "1x", " 1", "1 ", "--1", "0x10", "1e5e5"] {
            assert_eq!(parse_decimal(t), None, "{t:?}");
        }
        assert_eq!(parse_decimal("1e99999"), Some(f64::INFINITY));
    }

    #[test]
    fn a_full_buffer_cuts_and_says_so() {
        use core::fmt::Write;
        // `written`, which fits, then `more`, which does not, into 16 bytes: what the buffer holds, marked as cut.
        let cut = |written: &str, more: &str| {
            let mut b = TextBuf::<16>::default();
            assert!(b.write_str(written).is_ok() && b.write_str(more).is_err() && b.truncated());
            // Nothing is written after the cut.
            let held = b.as_str().to_string();
            assert!(b.write_str("more").is_err() && b.as_str() == held);
            b.clear();
            assert!(write!(b, "ok").is_ok() && b.as_str() == "ok" && !b.truncated());
            held
        };
        assert_eq!(cut("ok ", "a long reply that does not fit"), "ok a long re...\n");
        // A cut that falls inside a character backs off to its start: the text stays UTF-8 (`as_str` would give "").
        assert_eq!(cut("ok ", "abcdefgh\u{b5}m and more"), "ok abcdefgh...\n");
        // With less room left than the marker takes, the marker takes the end of what was written: the line still
        // ends, and nothing is written past the end; at a character's start.
        assert_eq!(cut("ok 12345678901", "abc"), "ok 123456789...\n");
        assert_eq!(cut("ok 12345678\u{b5}x", "abc"), "ok 12345678...\n");
        // Exactly the marker's room left: all that was written is kept.
        assert_eq!(cut("ok 123456789", "abcde"), "ok 123456789...\n");
        // A buffer smaller than the marker holds as much of it as fits.
        let mut tiny = TextBuf::<2>::default();
        assert!(tiny.write_str("abc").is_err());
        assert_eq!((tiny.as_str(), tiny.truncated()), ("..", true));
    }
}
