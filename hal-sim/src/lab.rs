//! The firmware on the simulated board: its interrupt body ([`Instrument`]), its command side ([`Controller`]) and
//! its console's loop (lines in, replies, the recording's tuning lines and frames out), wired as in
//! `src/bin/nanopos-fw/firmware.rs`, with the board behind the same HAL trait. `nanopos-sim console` runs it on a
//! terminal; the host tests (`tests/instrument.rs`) drive it sample by sample.

use crate::board::{BoardSettings, SimBoard};
use crate::sim::Scenario;
use nanopos_id::console::{write_record_end, Controller, Rest, REPLY_BYTES};
use nanopos_id::control::{parse, Command, LineBuffer, ParseError};
use nanopos_id::hal::StageBoard;
use nanopos_id::instrument::Instrument;
use nanopos_id::pipeline::{PipelineSettings, SampleOutput};
use nanopos_id::record::{encode_frame, RawSample, FRAME_MAX_BYTES, FRAME_SAMPLES};
use nanopos_id::text::TextBuf;
use nanopos_id::StageParams;

/// The board, the interrupt's state and the command side.
pub struct Lab {
    /// The simulated board.
    pub board: SimBoard,
    /// The interrupt's state, in the firmware's f32.
    pub isr: Instrument<f32>,
    /// The command side (the console task's).
    pub ctl: Controller,
    /// The console's line assembly.
    pub line: LineBuffer,
    /// Everything sent back on the serial link: replies, the recording's tuning lines; its frames only where a
    /// line found the recording stopped (its last frames and end line, which go out before the line's reply). The
    /// others are the caller's to take, where the console task would send them: [`Lab::drain_recording`].
    pub link: String,
}

impl Default for Lab {
    fn default() -> Self {
        Self::new()
    }
}

impl Lab {
    /// The paper's stage and board ([`Scenario::Prbs`] over 200 s: the payload comes off at 100 s), the PRBS
    /// running from the start, as the firmware starts.
    pub fn new() -> Self {
        Self::with_stage(None)
    }

    /// [`Lab::new`], with the stage `stage` (payload on and off alike) instead of the paper's.
    pub fn with_stage(stage: Option<StageParams<f64>>) -> Self {
        let (board, settings) = Self::settings(stage);
        Self::on_board(board, settings)
    }

    /// The firmware on a board of `board_settings` (say [`Lab::settings`]' with the payload's change moved or the
    /// piezo's gain drifting), started with the pipeline `settings`.
    pub fn on_board(board_settings: BoardSettings, settings: PipelineSettings) -> Self {
        let board = SimBoard::new(board_settings);
        let ctl = Controller::new(settings, board.description(), true).expect("the paper's settings design");
        let isr = Instrument::new(ctl.config(), &ctl.tuning());
        Lab { board, isr, ctl, line: LineBuffer::default(), link: String::new() }
    }

    /// The firmware on the paper's board ([`Lab::settings`]`(None)`) changed by `edit`, with the paper's pipeline.
    pub fn with_board(edit: impl FnOnce(&mut BoardSettings)) -> Self {
        let (mut board, settings) = Lab::settings(None);
        edit(&mut board);
        Lab::on_board(board, settings)
    }

    /// The board's and the pipeline's settings of [`Lab::with_stage`]: the paper's experiment ([`Scenario::Prbs`]
    /// over 200 s), with `stage` (payload on and off alike) instead of the paper's stage.
    pub fn settings(stage: Option<StageParams<f64>>) -> (BoardSettings, PipelineSettings) {
        let (mut board, settings) = Scenario::Prbs.settings(200.0, 1);
        if let Some(p) = stage {
            (board.plant.before, board.plant.after) = (p, p);
        }
        (board, settings)
    }

    /// Bytes typed on the link (lines ended by `\n`, `\r` or both, as a terminal sends them): every line they
    /// complete is executed, its change posted and applied by one sample, as the firmware's console does. Returns
    /// the replies; [`Lab::link`] has them too, each followed by the recording's tuning lines when due.
    pub fn send_bytes(&mut self, bytes: &[u8]) -> String {
        let mut replies = String::new();
        // As the firmware reads its receive buffer, on a link that loses nothing.
        let mut line = core::mem::take(&mut self.line);
        for parsed in line.read(bytes, false, usize::MAX) {
            // As the firmware: a recording that stopped ends before the line, its last frames and end line on the
            // link ahead of the reply.
            if self.ctl.recording_open() && !self.isr.record_status().active {
                let tail = self.drain_recording();
                self.link.push_str(&tail);
            }
            replies.push_str(&self.execute(parsed));
        }
        self.line = line;
        replies
    }

    /// The reply to `status`, not sent on the link (what the firmware's log shows, at 10 Hz), whatever part of a
    /// line the link has received.
    pub fn status_reply(&mut self) -> String {
        let at = self.link.len();
        let reply = self.execute(parse(b"status"));
        self.link.truncate(at);
        reply
    }

    /// One line, parsed: executed and answered, as the firmware's console does.
    fn execute(&mut self, parsed: Result<Command, ParseError>) -> String {
        let mut replies = String::new();
        // The firmware's buffer: every part of every reply fits it (the widest, `status`'s, is tested).
        let mut reply = TextBuf::<REPLY_BYTES>::default();
        let (change, mut rest) = match parsed {
            Ok(cmd) => {
                let isr = &self.isr;
                self.ctl.execute(cmd, || isr.status(), &mut reply)
            }
            Err(e) => {
                self.ctl.refuse(e, &mut reply);
                (None, Rest::none())
            }
        };
        if let Some(c) = change {
            // Nothing else posts, and each change is applied at once: the slot is free.
            assert!(self.isr.post(c).is_ok(), "a change was left pending");
            self.isr.sample(&mut self.board);
            assert!(!self.isr.change_pending(), "the sample applied the change");
        }
        loop {
            assert!(!reply.truncated(), "a reply's part does not fit the console's buffer: {}", reply.as_str());
            self.link.push_str(reply.as_str());
            replies.push_str(reply.as_str());
            reply.clear();
            if !rest.write_next(&self.ctl, &mut reply) {
                break;
            }
        }
        // As the firmware: the recording's tuning lines after the reply, stamped with the sample the change
        // applied to.
        if self.ctl.take_tuning_due() {
            for k in 0.. {
                reply.clear();
                if !self.ctl.write_tuning_line(k, self.isr.changed_at(), &mut reply) {
                    break;
                }
                self.link.push_str(reply.as_str());
            }
        }
        replies
    }

    /// [`Lab::send_bytes`] of a text.
    pub fn send(&mut self, text: &str) -> String {
        self.send_bytes(text.as_bytes())
    }

    /// One sample of the interrupt.
    pub fn sample(&mut self) -> SampleOutput<f32> {
        self.isr.sample(&mut self.board)
    }

    /// `n` samples.
    pub fn run(&mut self, n: usize) -> Vec<SampleOutput<f32>> {
        (0..n).map(|_| self.sample()).collect()
    }

    /// The recording's frames the firmware's console would send now: every whole frame while it records; once it
    /// stopped, the rest and its end line (and the command side learns that it ended). Empty when nothing is due.
    pub fn drain_recording(&mut self) -> String {
        let mut out = String::new();
        let (mut samples, mut frame) = ([RawSample::default(); FRAME_SAMPLES], [0u8; FRAME_MAX_BYTES]);
        loop {
            let st = self.isr.record_status();
            if st.active && st.buffered < FRAME_SAMPLES {
                break;
            }
            if st.buffered > 0 {
                let (first, n) = self.isr.drain_recorded(&mut samples);
                let len = encode_frame(first, &samples[..n], &mut frame);
                out.push_str(core::str::from_utf8(&frame[..len]).expect("frames are ASCII"));
                continue;
            }
            if !st.active && self.ctl.recording_open() {
                // In the console's reply buffer, as the firmware writes it (the longest end line is 70 bytes).
                let mut end = TextBuf::<REPLY_BYTES>::default();
                let _ = write_record_end(&st, &mut end);
                out.push_str(end.as_str());
                self.ctl.record_ended();
            }
            break;
        }
        out
    }
}
