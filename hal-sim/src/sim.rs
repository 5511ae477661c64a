//! A simulated stage driven by the real pipeline: the job the firmware does, on the host, faster than real time.

use crate::board::{BoardSettings, SimBoard};
use nanopos_id::estimator::EstimatorBank;
use nanopos_id::excitation::ExcitationDesign;
use nanopos_id::hal::{run_sample, run_sample_adding, StageBoard};
use nanopos_id::pipeline::{Pipeline, PipelineConfig, PipelineSettings, SampleOutput, SettingsError};
use nanopos_id::StageParams;

/// The paper's experiments.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scenario {
    /// PRBS, 1 V, content 0-1 kHz.
    Prbs,
    /// Smoothed triangle, 10 Hz, 1 V.
    Triangle,
    /// Multisine, 200-800 Hz, the power of a 1 V sine (not in the paper: the firmware's `excite multisine 1 200 800`).
    Multisine,
}

impl Scenario {
    /// The excitation.
    pub fn excitation(self) -> ExcitationDesign {
        match self {
            Scenario::Prbs => ExcitationDesign::PAPER_PRBS,
            Scenario::Triangle => ExcitationDesign::PAPER_TRIANGLE,
            Scenario::Multisine => ExcitationDesign::multisine(200.0, 800.0, 1.0),
        }
    }

    /// The float64 reference's noise seed for this input (the multisine, which it did not run: the next).
    pub fn default_seed(self) -> u64 {
        match self {
            Scenario::Prbs => 1,
            Scenario::Triangle => 2,
            Scenario::Multisine => 3,
        }
    }

    /// Board and pipeline of the paper's experiment: payload on, removed at half of `duration_s`.
    pub fn settings(self, duration_s: f64, seed: u64) -> (BoardSettings, PipelineSettings) {
        let mut board = BoardSettings { seed, ..BoardSettings::default() };
        let samples = (duration_s / board.plant.sample_period_s).round() as u64;
        board.plant.change_at_sample = samples / 2;
        let pipeline = PipelineSettings {
            sample_rate_hz: 1.0 / board.plant.sample_period_s,
            excitation: self.excitation(),
            probe: board.probe,
            amplifier: board.amplifier,
            ..PipelineSettings::default()
        };
        (board, pipeline)
    }
}

/// One sample of a run, as `simulate` writes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Record {
    /// Time of the sample, s.
    pub t_s: f64,
    /// The command in effect over this sample period, V.
    pub u_v: f64,
    /// The probe reading this sample, um.
    pub y_um: f64,
    /// The true stage parameters this sample.
    pub truth: StageParams<f64>,
}

/// The simulated board and the pipeline that drives it.
pub struct Simulation<E> {
    /// The board.
    pub board: SimBoard,
    /// The pipeline state.
    pub pipeline: Pipeline<f64, E>,
    /// The pipeline configuration.
    pub config: PipelineConfig<f64>,
}

impl<E: EstimatorBank<f64>> Simulation<E> {
    /// Design the pipeline for the board's converters and put both at rest.
    pub fn new(board: BoardSettings, pipeline: &PipelineSettings, estimators: E) -> Result<Self, SettingsError> {
        let board = SimBoard::new(board);
        let config = pipeline.design(&board.description())?;
        Ok(Simulation { pipeline: Pipeline::new(&config, estimators), board, config })
    }

    /// One sample.
    pub fn step(&mut self) -> (Record, SampleOutput<f64>) {
        self.step_with(None::<fn(f64) -> f64>)
    }

    /// One sample, the excitation added to an external command, V, `command(y_um)` of this sample's reading
    /// ([`nanopos_id::pipeline::Pipeline::step_adding`]).
    pub fn step_adding(&mut self, command: impl FnOnce(f64) -> f64) -> (Record, SampleOutput<f64>) {
        self.step_with(Some(command))
    }

    fn step_with(&mut self, command: Option<impl FnOnce(f64) -> f64>) -> (Record, SampleOutput<f64>) {
        let k = self.board.plant().sample();
        let truth = self.board.plant().params();
        let out = match command {
            None => run_sample(&mut self.board, &mut self.pipeline, &self.config),
            Some(v) => run_sample_adding(&mut self.board, &mut self.pipeline, &self.config, v),
        };
        let record = Record { t_s: k as f64 * self.config.sample_period_s, u_v: out.u_v, y_um: out.y_um, truth };
        (record, out)
    }
}
