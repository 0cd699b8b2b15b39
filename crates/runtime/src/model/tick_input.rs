//! The daemon's entry to the streaming forecaster: one resampled
//! [`TickInput`] per tick, turned into the same arrays `Window::from_ticks`
//! builds (the plan window sampled from the tick's latest plan on the tick
//! grid, the frame as CHW in `[0, 1]`), then [`StreamingForecaster::push_parts`].

use super::file::ModelError;
use super::streaming::StreamingForecaster;
use crate::clock::TickGrid;
use crate::streams::sample::Plan;
use crate::window::{TickInput, WindowSpec};

impl StreamingForecaster {
    /// The window spec of the loaded model (for `check_compatible` and the ring).
    pub fn window_spec(&self) -> WindowSpec {
        self.model().meta.window_spec()
    }

    /// Adds one tick. Streams the model's ablation does not use may be absent.
    pub fn push(&mut self, input: &TickInput) -> Result<(), ModelError> {
        let meta = &self.model().meta;
        let s = meta.config.frame_size;
        let tick = input.tick;
        let joints = input
            .joints_rad
            .as_ref()
            .ok_or_else(|| ModelError::Input(format!("tick {tick}: no joint angles yet")))?;
        let frame = if meta.ablation.uses_vision() {
            let held = input
                .frame
                .as_ref()
                .ok_or_else(|| ModelError::Input(format!("tick {tick}: no camera frame yet")))?;
            let (w, h) = held.dimensions();
            if w as usize != s || h as usize != s {
                return Err(ModelError::Input(format!(
                    "tick {tick}: frame is {w}x{h}, the model needs {s}x{s}"
                )));
            }
            // Decoded on arrival in the daemon (borrowed here); an episode
            // read with compressed frames decodes it now.
            let f = held
                .decoded()
                .map_err(|e| ModelError::Input(format!("tick {tick}: frame: {e}")))?;
            let mut chw = vec![0.0f32; 3 * s * s];
            f.write_chw(&mut chw, s * s);
            Some(chw)
        } else {
            None
        };
        // A tick without a plan yet is taken: only the newest tick's plan is
        // read, and the forecast refuses a window whose newest tick has none.
        let plan = match &input.plan {
            Some(p) if meta.ablation.uses_plan() && meta.config.trajectory.reads_plan() => {
                Some(self.plan_window(tick, p)?)
            }
            _ => None,
        };
        self.push_parts(tick, joints, frame.as_deref(), plan.as_deref())
    }

    /// After the forecast of `input`'s tick: the trajectory features of the
    /// next tick, computed now from the same plan message
    /// ([`StreamingForecaster::precompute_plan`]). If no new plan arrives
    /// before that tick, its forecast uses them and waits only for the
    /// joints, the frame, and the classifier. A model without a plan input,
    /// or a tick without a plan, does nothing.
    pub fn precompute_next(&mut self, input: &TickInput) -> Result<(), ModelError> {
        let meta = &self.model().meta;
        if !(meta.ablation.uses_plan() && meta.config.trajectory.reads_plan()) {
            return Ok(());
        }
        let Some(p) = input.plan.as_ref() else {
            return Ok(());
        };
        let next = input.tick + 1;
        let rows = self.plan_window(next, p)?;
        self.precompute_plan(next, &rows)
    }

    /// The plan window of tick `tick`: `plan` sampled on the tick grid at
    /// ticks `tick - N + 1 ..`, as many rows as the model reads (`N + h_K`,
    /// or `N` for historical-only: the forecaster cuts the same rows).
    fn plan_window(&self, tick: i64, plan: &Plan) -> Result<Vec<f32>, ModelError> {
        let meta = &self.model().meta;
        let (n, c) = (meta.n_ticks, meta.config.n_joints);
        // Only the plan needs the grid: no window spec (joint names and
        // all) is built per tick.
        let grid = TickGrid::new(meta.rate_hz)
            .map_err(|e| ModelError::Input(format!("tick grid: {e}")))?;
        let first_tick = tick - n as i64 + 1;
        let mut out = vec![0.0f32; meta.config.plan_len() * c];
        for (i, row) in out.chunks_exact_mut(c).enumerate() {
            plan.sample_into(grid.stamp_ns(first_tick + i as i64), row);
        }
        Ok(out)
    }
}

impl super::file::ModelMeta {
    /// The window this model reads: the spec of the ring, of training
    /// windows and of replayed episodes.
    pub fn window_spec(&self) -> WindowSpec {
        WindowSpec {
            n_ticks: self.n_ticks,
            max_horizon_ticks: self.config.max_horizon_ticks(),
            rate_hz: self.rate_hz,
            joint_names: self.joint_names.clone(),
            frame_size: self.frame_size,
        }
    }

    /// Refuses a window spec the model was not trained for, saying what differs.
    pub fn check_compatible(&self, spec: &WindowSpec) -> Result<(), ModelError> {
        self.check_compatible_with(
            &spec.joint_names,
            spec.rate_hz,
            spec.n_ticks,
            spec.max_horizon_ticks,
            spec.frame_size,
        )
    }
}

impl super::file::LoadedModel {
    /// Whole-window forecast of a `Window` built by `window.rs`: `K` probabilities.
    pub fn forecast_window(&self, window: &crate::window::Window) -> Result<Vec<f32>, ModelError> {
        self.forecast_arrays(&window.joints, &window.plan, &window.frames)
    }
}
