//! The recording stream: raw `(u, y)` converter codes of every sample, as text lines a serial terminal can capture,
//! and the host's way back to volts and micrometres.
//!
//! A recording is a header line, then frames:
//!
//! ```text
//! # nanopos-record v2 rate_hz=10000 delay=1 u_v_per_code=0.0048828125 u_v_offset=-10 y_um_per_code=0.00152587890625 y_um_offset=-50 crc=29b1
//! R00000000a3f2 <base64 of up to 48 samples> 1c0f
//! R00000000a422 ...
//! # nanopos-record end samples=2048 overflow=0 crc=3faa
//! ```
//!
//! - **Header:** the sample rate and the affine maps from codes to the command in volts (`u`) and the probe reading
//!   in micrometres (`y`), in the configuration of the moment, with enough digits to be exact for these converters;
//!   last, ` crc=` and the CRC-16 of everything before it (4 hex digits), as every line of the recording has: a
//!   changed digit in a scaling or the rate would otherwise mis-scale or mis-time the whole recording without a
//!   trace. (`v1`, before the header and the end line had it, is still read, unchecked.)
//! - **Frame:** `R`, the index of its first sample since the board started (12 hex digits), a space, the samples in
//!   standard base64 without padding (each sample 4 bytes: the DAC code *in effect* over the sample period, then the
//!   probe code read at its start, both little-endian `u16`), a space, and the CRC-16/CCITT-FALSE of everything
//!   before that space (4 hex digits). Frames follow each other without gaps: a recording stops at the first sample
//!   the board could not keep (its buffer full because the link is slower than the stream), and says so.
//! - **End:** a line with the number of samples recorded and whether the recording ended by overflow, and its CRC-16
//!   as the header's. The count tells a capture that lost frames at the recording's start or end, where no
//!   frame's index shows the gap.
//! - **Tuning:** after the header, before the first frame, one line per tuning key ([`TuningKey::ALL`]) with the
//!   values the estimators run, `# nanopos-tuning at=1000 ekf q 3d719799812dea11 ... crc=XXXX`: the index of the
//!   first sample they ran on (here the recording's first), the words of the console's `tune`, then each value as
//!   the 16 hex digits of its f64 bits (exact, so that a replay with them is the board's to the bit); and again, all
//!   of them, after each change of the tuning while the recording runs, with the sample the change applied to (the
//!   estimators whose tuning it changed restarted there, which a replay from the start does not do). `decode` turns the
//!   recording's first into the TOML file `identify --tuning` reads. Their tag is not `# nanopos-record`: a decoder of
//!   the first v2 firmware takes every line that starts so for the next recording's header, and skips these.
//!
//! Any other line (command replies, `ok ...`) is not part of the recording: a capture of the whole serial stream
//! converts as is.
//!
//! **Throughput.** 48 samples take 64 base64 characters per 12 bytes, 256 for the frame's 192, plus 20 of framing:
//! 276 bytes per 4.8 ms, 57.5 kB/s, 575 kbit/s with start and stop bits. Continuous recording at 10 kHz needs the
//! link at 921 600 baud (62 % of it); at 115 200 baud only bursts that fit the board's buffer
//! ([`crate::instrument::RECORD_BUFFER`] samples, 0.1 s) are complete. The tuning lines, 1 408 bytes with the
//! PRBS preset at sample 777 (19 more for each further digit of the sample index), hold the frames back by 15 ms
//! at 921 600 baud (at the start, and at a change of the tuning), which the buffer covers and the link's 38 % to
//! spare catches up in 25 ms; a burst that fits the buffer is complete at any rate, as before.

use crate::estimators::TuningKey;

/// Samples per frame.
pub const FRAME_SAMPLES: usize = 48;
/// Longest frame line, bytes, with its `\n`.
pub const FRAME_MAX_BYTES: usize = 1 + 12 + 1 + (FRAME_SAMPLES * 4 * 4).div_ceil(3) + 1 + 4 + 1;
/// The header's first words.
pub const HEADER_TAG: &str = "# nanopos-record v2";
/// The header's first words in the first version of the format, whose header and end line had no CRC.
pub const HEADER_TAG_V1: &str = "# nanopos-record v1";
/// The end line's first word.
pub const END_TAG: &str = "# nanopos-record end";

/// A tuning line's first words (see the module's doc).
pub const TUNING_TAG: &str = "# nanopos-tuning";

/// Write the tuning line of `key` with `values` (its [`TuningKey::len`] values), in effect from sample `at`, with its
/// CRC and `\n`.
pub fn write_tuning_line(
    out: &mut impl core::fmt::Write,
    at: u64,
    key: TuningKey,
    values: &[f64],
) -> core::fmt::Result {
    struct Bits<'a>(&'a [f64]);
    impl core::fmt::Display for Bits<'_> {
        fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
            self.0.iter().try_for_each(|v| {
                let mut word = *b" 0000000000000000";
                write_hex(v.to_bits(), &mut word[1..]);
                f.write_str(core::str::from_utf8(&word).unwrap_or_default())
            })
        }
    }
    let words = match key.path() {
        ("", name) => ("", "", name),
        (section, name) => (section, " ", name),
    };
    write_checked_line(out, format_args!("{TUNING_TAG} at={at} {}{}{}{}", words.0, words.1, words.2, Bits(values)))
}

/// Write every tuning line of `tuning` in effect from sample `at`, in [`TuningKey::ALL`]'s order (the console writes
/// them a line at a time).
pub fn write_tuning_lines(
    out: &mut impl core::fmt::Write,
    at: u64,
    tuning: &crate::estimators::Tuning,
) -> core::fmt::Result {
    TuningKey::ALL.into_iter().try_for_each(|key| write_tuning_line(out, at, key, &tuning.get(key)[..key.len()]))
}

/// A tuning line read back.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TuningLine {
    /// The first sample the values were in effect for.
    pub at: u64,
    /// Which.
    pub key: TuningKey,
    /// Its [`TuningKey::len`] values, then zeros.
    pub values: [f64; 5],
}

/// Why a tuning line was not read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TuningLineError {
    /// Its CRC does not match: changed or cut in transfer.
    Damaged,
    /// Intact, but of a key or a number of values this tuning does not have (a later firmware's).
    Unknown,
}

/// A tuning line (without its `\n`).
pub fn read_tuning_line(line: &str) -> Result<TuningLine, TuningLineError> {
    use TuningLineError::{Damaged, Unknown};
    let body = checked_body(line).ok_or(Damaged)?;
    let mut words = body.strip_prefix(TUNING_TAG).ok_or(Unknown)?.split_ascii_whitespace();
    let at = words.next().and_then(|w| w.strip_prefix("at=")).and_then(|n| n.parse().ok()).ok_or(Unknown)?;
    let first = words.next().ok_or(Unknown)?;
    let key = match TuningKey::parse("", first) {
        Some(key) => key,
        None => TuningKey::parse(first, words.next().ok_or(Unknown)?).ok_or(Unknown)?,
    };
    let mut values = [0.0; 5];
    let mut n = 0;
    for word in words {
        let bits = parse_hex(word.as_bytes()).filter(|_| word.len() == 16 && n < key.len()).ok_or(Unknown)?;
        values[n] = f64::from_bits(bits);
        n += 1;
    }
    if n != key.len() {
        return Err(Unknown);
    }
    Ok(TuningLine { at, key, values })
}

/// One recorded sample: the converter codes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RawSample {
    /// DAC code in effect over the sample period.
    pub u_code: u16,
    /// Probe code read at the start of the sample period.
    pub y_code: u16,
}

const B64: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

/// CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF).
pub fn crc16(bytes: &[u8]) -> u16 {
    crc16_update(0xFFFF, bytes)
}

/// [`crc16`] continued over `bytes` from `crc`.
fn crc16_update(mut crc: u16, bytes: &[u8]) -> u16 {
    for &b in bytes {
        crc ^= (b as u16) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 { (crc << 1) ^ 0x1021 } else { crc << 1 };
        }
    }
    crc
}

/// Passes text on and keeps the CRC-16 of it: a line's checksum without holding the line.
struct CrcWrite<'a, W: core::fmt::Write> {
    out: &'a mut W,
    crc: u16,
}

impl<W: core::fmt::Write> core::fmt::Write for CrcWrite<'_, W> {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        self.crc = crc16_update(self.crc, s.as_bytes());
        self.out.write_str(s)
    }
}

/// Write `line` and ` crc=` with the CRC-16 of `line` (4 hex digits), then `\n`: the header's and the end line's form.
pub fn write_checked_line(out: &mut impl core::fmt::Write, line: core::fmt::Arguments) -> core::fmt::Result {
    let mut w = CrcWrite { out, crc: 0xFFFF };
    core::fmt::Write::write_fmt(&mut w, line)?;
    let crc = w.crc;
    writeln!(out, " crc={crc:04x}")
}

/// The line without its ` crc=XXXX` if that is the CRC-16 of what precedes it (see [`write_checked_line`]); `None`
/// if the line has no CRC, or another.
pub fn checked_body(line: &str) -> Option<&str> {
    let (body, crc) = line.rsplit_once(" crc=")?;
    let crc = u16::from_str_radix(crc, 16).ok().filter(|_| crc.len() == 4)?;
    (crc16(body.as_bytes()) == crc).then_some(body)
}

/// `v`'s low `out.len()` hex digits into `out`, most significant first.
fn write_hex(v: u64, out: &mut [u8]) {
    let n = out.len();
    for (i, c) in out.iter_mut().enumerate() {
        *c = b"0123456789abcdef"[((v >> (4 * (n - 1 - i))) & 0xF) as usize];
    }
}

/// Write the frame of `samples` (at most [`FRAME_SAMPLES`]) starting at sample `first_index` into `out`; returns its
/// length in bytes, `\n` included.
pub fn encode_frame(first_index: u64, samples: &[RawSample], out: &mut [u8; FRAME_MAX_BYTES]) -> usize {
    let samples = &samples[..samples.len().min(FRAME_SAMPLES)];
    out[0] = b'R';
    write_hex(first_index, &mut out[1..13]);
    out[13] = b' ';
    let mut n = 14;
    let (mut acc, mut bits) = (0u32, 0u32);
    for s in samples {
        for byte in [s.u_code as u8, (s.u_code >> 8) as u8, s.y_code as u8, (s.y_code >> 8) as u8] {
            acc = (acc << 8) | byte as u32;
            bits += 8;
            while bits >= 6 {
                bits -= 6;
                out[n] = B64[((acc >> bits) & 63) as usize];
                n += 1;
            }
        }
    }
    if bits > 0 {
        out[n] = B64[((acc << (6 - bits)) & 63) as usize];
        n += 1;
    }
    let crc = crc16(&out[..n]);
    out[n] = b' ';
    write_hex(crc as u64, &mut out[n + 1..n + 5]);
    out[n + 5] = b'\n';
    n + 6
}

/// Why a frame line did not decode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameError {
    /// Not `R`, 12 hex digits, a space, base64, a space, 4 hex digits.
    Malformed,
    /// The checksum does not match: the line was damaged on the way.
    Checksum,
    /// The payload is not a whole number of samples, or more than a frame holds.
    Length,
}

impl core::fmt::Display for FrameError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            FrameError::Malformed => "not a recording frame (R, 12 hex digits, base64 samples, 4 hex digits)",
            FrameError::Checksum => "checksum mismatch: the line was damaged in transfer",
            FrameError::Length => "payload is not a whole number of samples (at most 48)",
        })
    }
}

fn parse_hex(s: &[u8]) -> Option<u64> {
    s.iter().try_fold(0u64, |acc, &c| Some((acc << 4) | (c as char).to_digit(16)? as u64))
}

/// Decode a frame line (without its `\n`; a trailing `\r` is ignored) into `out`; returns the first sample's index
/// and the number of samples.
pub fn decode_frame(line: &[u8], out: &mut [RawSample; FRAME_SAMPLES]) -> Result<(u64, usize), FrameError> {
    let line = line.strip_suffix(b"\r").unwrap_or(line);
    if line.len() < 19 || line[0] != b'R' || line[13] != b' ' || line[line.len() - 5] != b' ' {
        return Err(FrameError::Malformed);
    }
    let index = parse_hex(&line[1..13]).ok_or(FrameError::Malformed)?;
    let crc = parse_hex(&line[line.len() - 4..]).ok_or(FrameError::Malformed)?;
    let body = &line[..line.len() - 5];
    if crc16(body) as u64 != crc {
        return Err(FrameError::Checksum);
    }
    let payload = &body[14..];
    let mut bytes = [0u8; FRAME_SAMPLES * 4];
    let (mut acc, mut bits, mut n) = (0u32, 0u32, 0usize);
    for &c in payload {
        let v = B64.iter().position(|&b| b == c).ok_or(FrameError::Malformed)? as u32;
        acc = (acc << 6) | v;
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            if n == bytes.len() {
                return Err(FrameError::Length);
            }
            bytes[n] = (acc >> bits) as u8;
            n += 1;
        }
    }
    // What is left must be the zero padding of the last character.
    if n % 4 != 0 || bits >= 6 || acc & ((1 << bits) - 1) != 0 {
        return Err(FrameError::Length);
    }
    for (s, b) in out.iter_mut().zip(bytes[..n].chunks_exact(4)) {
        *s = RawSample { u_code: u16::from_le_bytes([b[0], b[1]]), y_code: u16::from_le_bytes([b[2], b[3]]) };
    }
    Ok((index, n / 4))
}

/// What the header says: the sample rate, and codes to physical units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RecordHeader {
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// The board's actuation delay (0 or 1 sample): informational, the codes are already those in effect.
    pub delay: u8,
    /// Command volts per DAC code.
    pub u_v_per_code: f64,
    /// Command volts of DAC code 0.
    pub u_v_offset: f64,
    /// Micrometres per probe code.
    pub y_um_per_code: f64,
    /// Micrometres of probe code 0.
    pub y_um_offset: f64,
}

impl RecordHeader {
    /// The firmware's on the NUCLEO-G474RE with its default front end (10 kHz; the 12-bit DAC over +-10 V, the
    /// 16-bit probe code over +-50 um): the header of the module's example.
    pub const EXAMPLE: Self = RecordHeader {
        rate_hz: 10_000.0,
        delay: 1,
        u_v_per_code: 20.0 / 4096.0,
        u_v_offset: -10.0,
        y_um_per_code: 100.0 / 65536.0,
        y_um_offset: -50.0,
    };

    /// Write the header line (with its CRC and `\n`).
    pub fn write(&self, out: &mut impl core::fmt::Write) -> core::fmt::Result {
        use crate::text::Num;
        write_checked_line(
            out,
            format_args!(
                "{HEADER_TAG} rate_hz={} delay={} u_v_per_code={} u_v_offset={} y_um_per_code={} y_um_offset={}",
                Num(self.rate_hz, 15),
                self.delay,
                Num(self.u_v_per_code, 15),
                Num(self.u_v_offset, 15),
                Num(self.y_um_per_code, 15),
                Num(self.y_um_offset, 15)
            ),
        )
    }

    /// `u` in V and `y` in um of a sample.
    pub fn physical(&self, s: RawSample) -> (f64, f64) {
        (self.u_v_offset + self.u_v_per_code * s.u_code as f64, self.y_um_offset + self.y_um_per_code * s.y_code as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_round_trip_and_damage_is_caught() {
        let samples: [RawSample; FRAME_SAMPLES] = core::array::from_fn(|i| RawSample {
            u_code: (i as u16).wrapping_mul(977) & 0x0FFF,
            y_code: (i as u16).wrapping_mul(40_503),
        });
        // A frame's body with its CRC made right for it, as `encode_frame` ends a line (without the `\n`).
        let with_crc = |body: &[u8]| {
            let mut line = body.to_vec();
            line.extend_from_slice(b" 0000");
            write_hex(crc16(body) as u64, &mut line[body.len() + 1..]);
            line
        };
        let mut buf = [0u8; FRAME_MAX_BYTES];
        for n in [0, 1, 2, 3, 47, 48] {
            let len = encode_frame(0x0012_3456_789a, &samples[..n], &mut buf);
            assert_eq!(buf[len - 1], b'\n');
            let line = &buf[..len - 1];
            let mut out = [RawSample::default(); FRAME_SAMPLES];
            assert_eq!(decode_frame(line, &mut out), Ok((0x0012_3456_789a, n)), "{n}");
            assert_eq!(out[..n], samples[..n]);
            if n == FRAME_SAMPLES {
                assert_eq!(len, FRAME_MAX_BYTES);
            }
            // One character changed anywhere is caught (the CRC detects every single-character error).
            for i in 0..line.len() {
                let mut bad = line.to_vec();
                bad[i] = if bad[i].eq_ignore_ascii_case(&b'a') { b'B' } else { b'A' };
                assert!(decode_frame(&bad, &mut out).is_err(), "{n} {i}");
            }
            // A truncated line is refused.
            assert!(decode_frame(&line[..line.len() - 6], &mut out).is_err());
            // The form is checked, not only the CRC: a frame but for its letter or the space after its index, with
            // the CRC made right for it, is not a frame; nor is a payload of part of a sample, or with a character
            // more (six bits of zeros: a whole number of bytes still).
            let body = &line[..line.len() - 5];
            for (i, c) in [(0, b'S'), (13, b'_')] {
                let mut bad = body.to_vec();
                bad[i] = c;
                assert_eq!(decode_frame(&with_crc(&bad), &mut out), Err(FrameError::Malformed), "{n} {i}");
            }
            assert_eq!(decode_frame(&with_crc(body), &mut out), Ok((0x0012_3456_789a, n)), "{n}");
            // Three characters: two bytes, half a sample; and a character of zeros after the samples.
            let (half, longer) = ([&body[..14], b"AAA"].concat(), [body, b"A"].concat());
            for bad in [half, longer] {
                assert_eq!(decode_frame(&with_crc(&bad), &mut out), Err(FrameError::Length), "{n}");
            }
        }
        assert_eq!(crc16(b"123456789"), 0x29B1);
    }

    /// Lines that are not what the board wrote, 200 000 of them: random bytes of random length (weighted to the
    /// frame's own alphabet, so that they get past its first checks), and the board's frame cut, grown, shortened and
    /// with runs of bytes replaced. None panics the readers `decode` reads a capture with (`decode_frame`,
    /// `read_tuning_line`, `checked_body`), and a damaged frame is taken with other samples only where the damage
    /// happens to keep the CRC-16 (1 in 65 536 of the frames that still parse: about 1.5 expected here).
    #[test]
    fn no_line_of_a_damaged_capture_panics_and_few_pass_for_a_frame() {
        let mut next = crate::xorshift64(0x5DEE_CE66_D1CE_4E5B);
        let mut below = |n: usize| (next() % n as u64) as usize;
        let samples: [RawSample; FRAME_SAMPLES] = core::array::from_fn(|i| RawSample {
            u_code: (i as u16 * 83) & 0x0FFF,
            y_code: (i as u16).wrapping_mul(40_503),
        });
        let mut buf = [0u8; FRAME_MAX_BYTES];
        let len = encode_frame(0x0000_0001_86a0, &samples, &mut buf);
        let good = buf[..len - 1].to_vec();
        let alphabet = b"R0123456789abcdefABCDEFghxyz+/= #-\x01\xff";
        let mut out = [RawSample::default(); FRAME_SAMPLES];
        let (mut parsed, mut changed) = (0, 0);
        for k in 0..200_000u32 {
            let n = below(4);
            let line: Vec<u8> = if k % 2 == 0 {
                let n = below(300);
                (0..n).map(|_| alphabet[below(alphabet.len())]).collect()
            } else {
                let mut l = good.clone();
                let at = below(l.len());
                let end = (at + 1 + n).min(l.len());
                match below(4) {
                    0 => l.truncate(at),
                    1 => {
                        let grown: Vec<u8> = (0..=n).map(|_| alphabet[below(alphabet.len())]).collect();
                        l.splice(at..at, grown);
                    }
                    2 => {
                        l.drain(at..end);
                    }
                    _ => {
                        for b in &mut l[at..end] {
                            *b = alphabet[below(alphabet.len())];
                        }
                    }
                }
                l
            };
            if let Ok((first, n)) = decode_frame(&line, &mut out) {
                parsed += (line != good) as u32;
                changed += (first != 0x0000_0001_86a0 || n != FRAME_SAMPLES || out[..n] != samples[..n]) as u32;
            }
            let text = String::from_utf8_lossy(&line);
            let _ = read_tuning_line(&text);
            let _ = checked_body(&text);
        }
        println!("{parsed} damaged frames parsed, {changed} of them with other samples");
        assert!(changed <= 6, "{changed} damaged frames taken with other samples");
    }

    /// The header and the end line carry the CRC of what precedes ` crc=`: one character changed anywhere, or the
    /// CRC missing, and the line is not taken as intact.
    #[test]
    fn a_checked_line_is_intact_only_as_written() {
        let mut text = crate::text::TextBuf::<256>::default();
        RecordHeader::EXAMPLE.write(&mut text).unwrap();
        let line = text.as_str().strip_suffix('\n').unwrap();
        let body = checked_body(line).unwrap();
        assert_eq!(
            body,
            "# nanopos-record v2 rate_hz=10000 delay=1 u_v_per_code=0.0048828125 u_v_offset=-10 \
             y_um_per_code=0.00152587890625 y_um_offset=-50"
        );
        assert!(line.ends_with(" crc=29b1"), "the module's example: {line}");
        for i in 0..line.len() {
            let mut bad = line.as_bytes().to_vec();
            bad[i] = if bad[i] == b'7' { b'8' } else { b'7' };
            assert_eq!(checked_body(core::str::from_utf8(&bad).unwrap()), None, "{i}");
        }
        assert_eq!(checked_body(body), None, "no CRC");
        let mut end = crate::text::TextBuf::<80>::default();
        write_checked_line(&mut end, format_args!("{END_TAG} samples={} overflow={}", 2048, 0)).unwrap();
        assert_eq!(end.as_str(), "# nanopos-record end samples=2048 overflow=0 crc=3faa\n");
        assert_eq!(checked_body(end.as_str().trim_end()), Some("# nanopos-record end samples=2048 overflow=0"));
    }

    /// Every key's line reads back its key and its values bit for bit, also values no decimal form with few digits
    /// holds; a line changed anywhere is damaged; an intact line of a key or a count this tuning lacks is unknown.
    #[test]
    fn tuning_lines_carry_every_key_exactly() {
        use crate::control::TuningPreset;
        let mut tuning = crate::estimators::Tuning::of(TuningPreset::Prbs);
        tuning.set(TuningKey::EkfR, &[0.1 + 0.2]).unwrap();
        tuning.set(TuningKey::Initial, &[5.000_000_000_000_01e5, 70.0 / 3.0, 6e6 * core::f64::consts::PI]).unwrap();
        for key in TuningKey::ALL {
            let values = tuning.get(key);
            let mut text = crate::text::TextBuf::<256>::default();
            write_tuning_line(&mut text, 0x0123_4567_89ab, key, &values[..key.len()]).unwrap();
            let line = text.as_str().strip_suffix('\n').unwrap();
            let TuningLine { at, key: read, values: got } = read_tuning_line(line).unwrap();
            assert_eq!((at, read), (0x0123_4567_89ab, key), "{line}");
            assert_eq!(
                got[..key.len()].iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                values[..key.len()].iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "{line}"
            );
            for i in 0..line.len() {
                let mut bad = line.as_bytes().to_vec();
                bad[i] = if bad[i] == b'7' { b'8' } else { b'7' };
                assert_eq!(read_tuning_line(core::str::from_utf8(&bad).unwrap()), Err(TuningLineError::Damaged), "{i}");
            }
        }
        let mut text = crate::text::TextBuf::<256>::default();
        write_tuning_line(&mut text, 1000, TuningKey::EkfR, &[1.5e-6]).unwrap();
        assert_eq!(text.as_str(), "# nanopos-tuning at=1000 ekf r 3eb92a737110e454 crc=34da\n");
        for (body, why) in [
            ("# nanopos-tuning at=1000 ekf r", "no value"),
            ("# nanopos-tuning at=1000 ekf r 3eb92a737110e454 3eb92a737110e454", "two values for one"),
            ("# nanopos-tuning at=1000 ekf q 3eb92a737110e454", "one value for five"),
            (
                "# nanopos-tuning at=1000 ekf q 3eb92a737110e454 3eb92a737110e454 3eb92a737110e454 3eb92a737110e454 \
                 3eb92a737110e454 3eb92a737110e454",
                "six values for five (not one written past the five)",
            ),
            ("# nanopos-tuning at=1000 ekf gain 3eb92a737110e454", "a key this tuning lacks"),
            ("# nanopos-tuning at=1000 ekf r 3eb92a737110e45", "15 digits"),
            ("# nanopos-tuning ekf r 3eb92a737110e454", "no sample"),
            ("# nanopos-tuning at=-1 ekf r 3eb92a737110e454", "a sample before the start"),
        ] {
            let mut line = crate::text::TextBuf::<256>::default();
            write_checked_line(&mut line, format_args!("{body}")).unwrap();
            assert_eq!(read_tuning_line(line.as_str().trim_end()), Err(TuningLineError::Unknown), "{why}");
        }
    }
}
