//! Per-tick inference: the daemon pushes one tick at a time and asks for a
//! forecast; per-frame and per-time-slice work is done once, not every tick.
//!
//! In: [`StreamingForecaster::push_parts`] with one tick's joint angles, frame
//! and plan window. Out: [`StreamingForecaster::forecast`], `K` probabilities.
//!
//! What is reused across ticks (all exact, equal to the whole-window forward):
//! - the low-pass of a frame, computed once when the frame enters;
//! - in the vision encoder, every time slice of every layer, kept by the
//!   absolute tick where it starts with the input slices it was computed
//!   from, and reused while those are the same (by identity: a slice whose
//!   value changes is a new one). Only the slices next to the window's two
//!   ends change (there "same" padding puts zeros), and the new ones. An
//!   output slice is the bias plus one term per time tap, one input slice
//!   each ([`HostConv::slice_terms`](super::host_conv::HostConv::slice_terms)); the terms
//!   of the input slices near the ends are kept too, so that a changed
//!   output slice computes only the terms of the inputs that changed.
//!
//! Motion, plan and classifier are recomputed every tick (their inputs all
//! move). The plan's features can be computed before their tick
//! ([`StreamingForecaster::precompute_plan`]): between two plan messages the
//! next tick's plan window is known once a tick is done.
//! Inference runs on the calling thread: the Flex backend is built without
//! its rayon feature, so no other thread is used.

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;

use burn::prelude::*;

use super::file::{host_logits, LoadedModel, ModelError};
use super::ranges::{record, Bounds, Excursion};
use super::vision::lowpass_frames;

/// One time slice of one vision layer: `[channels, h, w]` row-major.
#[derive(Debug, Clone)]
struct Slice {
    /// Absolute tick of the first frame the slice covers.
    key: i64,
    /// Its value; a slice whose value changes is a new allocation, so
    /// `Arc::ptr_eq` tells whether what was computed from it still holds.
    data: Arc<Vec<f32>>,
}

type Data = Arc<Vec<f32>>;

/// What one vision layer keeps from one tick to the next.
#[derive(Debug, Default, Clone)]
struct LayerCache {
    /// Output slice by key, with the `k` input slices it was computed from
    /// (`None`: the window's padding).
    outputs: HashMap<i64, (Vec<Option<Data>>, Data)>,
    /// One input slice's term through one time tap, by (input key, tap),
    /// with the input slice it is of; only of input slices near the
    /// window's ends, where output slices change.
    terms: HashMap<(i64, usize), (Data, Data)>,
    /// A time-pooled pair by its first key, with the two slices it is of.
    pooled: HashMap<i64, ([Data; 2], Data)>,
    /// Buffers of terms no longer kept, for the next terms.
    spare: Vec<Vec<f32>>,
}

/// Whether `kept` are the same slices as `now` (the same allocations).
fn same_slices(kept: &[Option<Data>], now: &[Option<&Slice>]) -> bool {
    kept.len() == now.len()
        && kept.iter().zip(now).all(|(a, b)| match (a, b) {
            (None, None) => true,
            (Some(a), Some(b)) => Arc::ptr_eq(a, &b.data),
            _ => false,
        })
}

/// One tick as the forecaster keeps it.
#[derive(Debug, Clone)]
struct TickState {
    tick: i64,
    joints_std: Vec<f32>,
    /// The measured angles as given, kept for a real-position model (its
    /// trajectory encoder reads them, standardised with the plan statistics).
    joints_rad: Option<Vec<f32>>,
    frame_lp: Option<Arc<Vec<f32>>>,
    /// Its joints and frame outside their bounds (usually none).
    excursions: Vec<Excursion>,
}

/// Forecasts tick by tick from a [`LoadedModel`].
#[derive(Debug)]
pub struct StreamingForecaster {
    model: LoadedModel,
    /// What every input is held to ([`Bounds::of`] the model; none: a
    /// file without measured ranges, nothing held).
    bounds: Option<Bounds>,
    ticks: VecDeque<TickState>,
    plan_std: Option<Vec<f32>>,
    /// The newest plan window's values outside their bounds.
    plan_excursions: Vec<Excursion>,
    /// Trajectory features computed ahead of their tick
    /// ([`StreamingForecaster::precompute_plan`]) with the standardised plan
    /// window they are of: used when the tick's window is that one.
    plan_ahead: Option<(Vec<f32>, Tensor<2>)>,
    /// Forecasts that used `plan_ahead`, for tests and benchmarks.
    plan_reused: u64,
    /// Per vision layer: its slices (after conv, ReLU, spatial pool) and terms.
    cache: Vec<LayerCache>,
    /// Vision slices computed so far (all layers), for tests and benchmarks.
    slices_computed: u64,
    /// Vision slice terms computed so far (all layers), for tests and benchmarks.
    terms_computed: u64,
    /// Kept terms summed into a computed slice, for tests and benchmarks.
    terms_reused: u64,
}

impl StreamingForecaster {
    /// A forecaster with an empty window.
    pub fn new(model: &LoadedModel) -> Self {
        let cfg = &model.meta.config;
        let layers = cfg.vision_channels.len();
        StreamingForecaster {
            model: model.clone(),
            bounds: Bounds::of(&model.meta),
            ticks: VecDeque::with_capacity(cfg.n_ticks + 1),
            plan_std: None,
            plan_excursions: Vec::new(),
            plan_ahead: None,
            plan_reused: 0,
            cache: vec![LayerCache::default(); layers],
            slices_computed: 0,
            terms_computed: 0,
            terms_reused: 0,
        }
    }

    /// The model it runs.
    pub fn model(&self) -> &LoadedModel {
        &self.model
    }

    /// Forgets every tick (e.g. after a stream gap).
    pub fn reset(&mut self) {
        self.ticks.clear();
        self.plan_std = None;
        self.plan_excursions.clear();
        self.plan_ahead = None;
        self.cache.fill_with(LayerCache::default);
    }

    /// The bounds the inputs are held to (none: the file has no ranges).
    pub fn bounds(&self) -> Option<&Bounds> {
        self.bounds.as_ref()
    }

    /// `value` of joint channel `j` (`plan`: of the trajectory input) held
    /// to its bound, if the model has bounds.
    fn clip(&self, plan: bool, j: usize, value: f32, out: &mut Vec<Excursion>) -> f32 {
        match &self.bounds {
            Some(b) => b.clip(plan, j, value, out),
            None => value,
        }
    }

    /// The inputs of the current window outside their bounds, the largest
    /// excursion of each (joints and frames of every tick in the window,
    /// the newest tick's plan window), in input order. Empty: every value
    /// the network reads is as given.
    pub fn excursions(&self) -> Vec<Excursion> {
        let mut out = Vec::new();
        for e in self
            .ticks
            .iter()
            .flat_map(|t| &t.excursions)
            .chain(&self.plan_excursions)
        {
            record(&mut out, e.clone());
        }
        out.sort_by_key(|e| e.input);
        out
    }

    /// Forecasts whose trajectory features were computed ahead of their
    /// tick ([`StreamingForecaster::precompute_plan`]).
    pub fn plan_reused(&self) -> u64 {
        self.plan_reused
    }

    /// Vision slices computed since the forecaster was made (every layer):
    /// how much vision work a tick did, independent of the machine's speed.
    pub fn slices_computed(&self) -> u64 {
        self.slices_computed
    }

    /// Vision slice terms (one input slice through one time tap) computed
    /// since the forecaster was made (every layer): the convolution work.
    pub fn terms_computed(&self) -> u64 {
        self.terms_computed
    }

    /// Vision slice terms kept from an earlier tick and summed again.
    pub fn terms_reused(&self) -> u64 {
        self.terms_reused
    }

    /// The trajectory encoder's first-block rows reused from the forward
    /// before (the plan window slid over the same plan) and those
    /// multiplied, since the forecaster was made.
    pub fn plan_rows(&self) -> (u64, u64) {
        self.model
            .network
            .plan_fused
            .as_ref()
            .map_or((0, 0), |p| p.tap_rows())
    }

    /// The oldest tick in the window, if any.
    pub fn first_tick(&self) -> Option<i64> {
        self.ticks.front().map(|t| t.tick)
    }

    /// The last tick pushed, if any.
    pub fn last_tick(&self) -> Option<i64> {
        self.ticks.back().map(|t| t.tick)
    }

    /// Whether `N` consecutive ticks are in the window.
    pub fn is_full(&self) -> bool {
        self.ticks.len() == self.model.meta.n_ticks
    }

    /// Adds tick `tick`: `joints_rad` `[C]` in model order; `frame` `[3, S, S]`
    /// in `[0, 1]` (needed by vision ablations); `plan_rad` the plan window
    /// `[N + h_K, C]` for this tick (needed by plan ablations whose
    /// trajectory input is cut from the plan, for the newest tick only: the
    /// window's plan is the newest tick's; a historical-only model reads
    /// its first `N` rows and accepts a window of just those). A tick that is
    /// not the successor of the last one starts a new window.
    pub fn push_parts(
        &mut self,
        tick: i64,
        joints_rad: &[f32],
        frame: Option<&[f32]>,
        plan_rad: Option<&[f32]>,
    ) -> Result<(), ModelError> {
        let meta = &self.model.meta;
        let cfg = &meta.config;
        let c = cfg.n_joints;
        if joints_rad.len() != c {
            return Err(ModelError::Input(format!(
                "tick {tick}: {} joint angles, the model needs {c}",
                joints_rad.len()
            )));
        }
        let mut joints_std = Vec::with_capacity(c);
        let mut excursions = Vec::new();
        for (j, &v) in joints_rad.iter().enumerate() {
            if !v.is_finite() {
                return Err(ModelError::Input(format!(
                    "tick {tick}: joint {} is not finite ({v})",
                    meta.joint_names[j]
                )));
            }
            let v = self.clip(false, j, v, &mut excursions);
            joints_std.push((v - meta.joint_mean[j]) / meta.joint_std[j]);
        }
        let frame_lp = if meta.ablation.uses_vision() {
            let s = cfg.frame_size;
            let f = frame.ok_or_else(|| {
                ModelError::Input(format!(
                    "tick {tick}: no camera frame, the {} model needs one",
                    meta.ablation
                ))
            })?;
            if f.len() != 3 * s * s {
                return Err(ModelError::Input(format!(
                    "tick {tick}: frame has {} values, expected 3 x {s} x {s}",
                    f.len()
                )));
            }
            if f.iter().any(|v| !v.is_finite()) {
                return Err(ModelError::Input(format!(
                    "tick {tick}: frame is not finite"
                )));
            }
            if let Some(b) = &self.bounds {
                b.check_frame(f, &mut excursions);
            }
            // P · x · Pᵀ per channel with the same tensor code as the whole-window path.
            let raw = Tensor::<5>::from_data(
                TensorData::new(f.to_vec(), [1, 3, 1, s, s]),
                &self.model.device,
            );
            let out: Vec<f32> = lowpass_frames(raw, cfg.lowpass_a)
                .into_data()
                .try_to_vec::<f32>()
                .map_err(|e| ModelError::Input(format!("tick {tick}: low-pass output: {e:?}")))?;
            Some(Arc::new(out))
        } else {
            None
        };
        if meta.ablation.uses_plan() && cfg.trajectory.reads_plan() {
            // Only the newest tick's plan window is read (it holds the
            // window's past and future plan): a tick without a plan clears
            // it, and the forecast of a window ending there is refused.
            let mut plan_excursions = Vec::new();
            self.plan_std = plan_rad
                .map(|p| self.standardised_plan(tick, p, &mut plan_excursions))
                .transpose()?;
            self.plan_excursions = plan_excursions;
        }
        if let Some(last) = self.ticks.back() {
            if tick != last.tick + 1 {
                tracing::debug!(tick, last = last.tick, "tick gap: window restarts");
                self.ticks.clear();
                self.cache.fill_with(LayerCache::default);
            }
        }
        let keep_raw = meta.ablation.uses_plan() && !cfg.trajectory.reads_plan();
        self.ticks.push_back(TickState {
            tick,
            joints_std,
            joints_rad: keep_raw.then(|| joints_rad.to_vec()),
            frame_lp,
            excursions,
        });
        if self.ticks.len() > cfg.n_ticks {
            self.ticks.pop_front();
        }
        Ok(())
    }

    /// The trajectory encoder's input for tick `tick`, standardised, from
    /// the plan window `plan_rad` (checked: length, finite values; each
    /// value held to its bound, excursions into `excursions`).
    fn standardised_plan(
        &self,
        tick: i64,
        plan_rad: &[f32],
        excursions: &mut Vec<Excursion>,
    ) -> Result<Vec<f32>, ModelError> {
        let meta = &self.model.meta;
        let cfg = &meta.config;
        let (l, c) = (cfg.plan_len(), cfg.n_joints);
        let p = cfg.trajectory_rows(&[], plan_rad);
        if p.len() != l * c {
            return Err(ModelError::Input(format!(
                "tick {tick}: plan window has {} values, expected {l} ticks x {c} joints",
                p.len()
            )));
        }
        let mut std = Vec::with_capacity(l * c);
        for (i, &v) in p.iter().enumerate() {
            if !v.is_finite() {
                return Err(ModelError::Input(format!(
                    "tick {tick}: plan not finite at offset {} joint {}",
                    i / c,
                    meta.joint_names[i % c]
                )));
            }
            let v = self.clip(true, i % c, v, excursions);
            std.push((v - meta.plan_mean[i % c]) / meta.plan_std[i % c]);
        }
        Ok(std)
    }

    /// Computes now the trajectory features of a later tick's plan window
    /// `plan_rad` (the same rows `push_parts` would be given), so that the
    /// forecast of that tick, if its window is exactly this one, does not
    /// wait for them. Between two plan messages the next tick's window is
    /// known as soon as a tick is done (the plan sampled on the tick grid),
    /// so the daemon computes it while it waits for the next joints. The
    /// features are the same computation on the same values: a forecast is
    /// bit for bit what it would have been. A model without a plan input
    /// does nothing.
    pub fn precompute_plan(&mut self, tick: i64, plan_rad: &[f32]) -> Result<(), ModelError> {
        let meta = &self.model.meta;
        if !(meta.ablation.uses_plan() && meta.config.trajectory.reads_plan()) {
            return Ok(());
        }
        let std = self.standardised_plan(tick, plan_rad, &mut Vec::new())?;
        let (l, c) = (meta.config.plan_len(), meta.config.n_joints);
        let plan =
            Tensor::<3>::from_data(TensorData::new(std.clone(), [1, l, c]), &self.model.device);
        if let Some(features) = self.model.network.plan_features(plan) {
            self.plan_ahead = Some((std, features));
        }
        Ok(())
    }

    /// While the window fills: computes the vision slices of the ticks pushed
    /// so far (those that will not change once the window is full are kept),
    /// so that the first forecast of a full window costs one tick's work, not
    /// a whole-window forward. Nothing to do for a model without vision or
    /// a full window.
    pub fn prepare(&mut self) -> Result<(), ModelError> {
        if self.model.meta.ablation.uses_vision() && !self.ticks.is_empty() && !self.is_full() {
            self.vision_features()?;
        }
        Ok(())
    }

    /// `K` fall probabilities for the current window (non-decreasing in the horizon).
    pub fn forecast(&mut self) -> Result<Vec<f32>, ModelError> {
        let meta = &self.model.meta;
        let cfg = &meta.config;
        let (n, c) = (cfg.n_ticks, cfg.n_joints);
        if !self.is_full() {
            return Err(ModelError::Input(format!(
                "window not full: {} of {n} ticks",
                self.ticks.len()
            )));
        }
        if meta.ablation.uses_plan() && cfg.trajectory.reads_plan() && self.plan_std.is_none() {
            return Err(ModelError::Input(format!(
                "tick {}: no plan, the {} model needs one",
                self.ticks.back().map_or(0, |t| t.tick),
                meta.ablation
            )));
        }
        let device = self.model.device.clone();
        let joints: Vec<f32> = self
            .ticks
            .iter()
            .flat_map(|t| t.joints_std.iter().copied())
            .collect();
        let joints = Tensor::<3>::from_data(TensorData::new(joints, [1, n, c]), &device);
        // Trajectory features computed ahead for exactly this window, or now.
        let ahead = match (&self.plan_ahead, &self.plan_std) {
            (Some((rows, features)), Some(now)) if rows == now => Some(features.clone()),
            _ => None,
        };
        let plan_features = match ahead {
            Some(f) => {
                self.plan_reused += 1;
                Some(f)
            }
            None => self
                .plan_input()?
                .and_then(|p| self.model.network.plan_features(p)),
        };
        let vision = if meta.ablation.uses_vision() {
            Some(self.vision_features()?)
        } else {
            None
        };
        let logits = self
            .model
            .network
            .forward_with_features(joints, plan_features, vision);
        Ok(self.model.meta.probabilities_of(&host_logits(logits)?))
    }

    /// The trajectory encoder's input `[1, L, C]` for the current window,
    /// standardised; `None` for a network without a plan input.
    fn plan_input(&self) -> Result<Option<Tensor<3>>, ModelError> {
        let meta = &self.model.meta;
        let cfg = &meta.config;
        let c = cfg.n_joints;
        let device = &self.model.device;
        Ok(if !meta.ablation.uses_plan() {
            None
        } else if cfg.trajectory.reads_plan() {
            self.plan_std.as_ref().map(|p| {
                Tensor::<3>::from_data(TensorData::new(p.clone(), [1, cfg.plan_len(), c]), device)
            })
        } else {
            // Real position: the window's measured angles, through the same
            // cut as the whole-window path, standardised as the plan.
            let raw: Vec<f32> = self
                .ticks
                .iter()
                .flat_map(|t| t.joints_rad.iter().flatten().copied())
                .collect();
            let rows = cfg.trajectory_rows(&raw, &[]);
            if rows.len() != cfg.plan_len() * c {
                return Err(ModelError::Input(format!(
                    "real-position input has {} values, expected {} ticks x {c} joints",
                    rows.len(),
                    cfg.plan_len()
                )));
            }
            // Held to the plan's bounds as the whole-window path holds them
            // (the joints' own excursions are reported per tick).
            let std: Vec<f32> = rows
                .iter()
                .enumerate()
                .map(|(i, &v)| {
                    let v = self.clip(true, i % c, v, &mut Vec::new());
                    (v - meta.plan_mean[i % c]) / meta.plan_std[i % c]
                })
                .collect();
            Some(Tensor::<3>::from_data(
                TensorData::new(std, [1, cfg.plan_len(), c]),
                device,
            ))
        })
    }

    /// Vision features `[1, F]` of the current window, reusing cached slices.
    fn vision_features(&mut self) -> Result<Tensor<2>, ModelError> {
        let cfg = self.model.meta.config.clone();
        let device = self.model.device.clone();
        let fused =
            self.model.network.vision_fused.clone().ok_or_else(|| {
                ModelError::Input("vision ablation without vision weights".into())
            })?;
        let window_start = self.ticks.front().map(|t| t.tick).unwrap_or(0);
        let mut slices: Vec<Slice> = Vec::with_capacity(cfg.n_ticks);
        for t in &self.ticks {
            let data = t
                .frame_lp
                .clone()
                .ok_or_else(|| ModelError::Input(format!("tick {}: no frame", t.tick)))?;
            slices.push(Slice { key: t.tick, data });
        }
        let mut c_in = 3usize;
        let mut hw = cfg.lowpassed_size();
        for li in 0..fused.slices.len() {
            let c_out = cfg.vision_channels[li];
            let t_len = slices.len();
            let out_len = c_out * (hw / 2) * (hw / 2);
            let conv = &fused.slices[li];
            let cache = &mut self.cache[li];
            // The kernel reaches `half` slices each way; `None` (zeros)
            // stands for the "same" padding where the window really ends.
            let (k, half) = (conv.k(), conv.k() / 2);
            let near = |pos: usize| -> Vec<Option<&Slice>> {
                (0..k)
                    .map(|kt| (pos + kt).checked_sub(half).and_then(|i| slices.get(i)))
                    .collect()
            };
            let term_of = |terms: &HashMap<(i64, usize), (Data, Data)>, s: &Slice, kt: usize| {
                terms
                    .get(&(s.key, kt))
                    .filter(|(of, _)| Arc::ptr_eq(of, &s.data))
                    .map(|(_, term)| term.clone())
            };
            // The output slices to compute (their inputs changed), and the
            // terms they need that are not kept, by input slice: each
            // input's terms are computed together (one padded copy).
            let mut out: Vec<Option<Data>> = vec![None; t_len];
            let mut stale: Vec<(usize, Vec<Option<&Slice>>)> = Vec::new();
            let mut wanted: Vec<Vec<usize>> = vec![Vec::new(); t_len];
            for pos in 0..t_len {
                let around = near(pos);
                if let Some((from, data)) = cache.outputs.get(&slices[pos].key) {
                    if same_slices(from, &around) {
                        out[pos] = Some(data.clone());
                        continue;
                    }
                }
                for (kt, s) in around.iter().enumerate() {
                    if let Some(s) = s {
                        if term_of(&cache.terms, s, kt).is_none() {
                            wanted[pos + kt - half].push(kt);
                        } else {
                            self.terms_reused += 1;
                        }
                    }
                }
                stale.push((pos, around));
            }
            for (i, kts) in wanted.iter().enumerate().filter(|(_, kts)| !kts.is_empty()) {
                let s = &slices[i];
                let terms = conv.slice_terms(&s.data, kts, hw, &mut cache.spare);
                self.terms_computed += kts.len() as u64;
                for (&kt, term) in kts.iter().zip(terms) {
                    cache
                        .terms
                        .insert((s.key, kt), (s.data.clone(), Arc::new(term)));
                }
            }
            for (pos, around) in stale {
                let terms: Vec<Data> = around
                    .iter()
                    .enumerate()
                    .filter_map(|(kt, s)| term_of(&cache.terms, (*s)?, kt))
                    .collect();
                let terms: Vec<&[f32]> = terms.iter().map(|t| t.as_slice()).collect();
                let data = Arc::new(conv.pooled_of_terms(&terms, hw));
                debug_assert_eq!(data.len(), out_len);
                self.slices_computed += 1;
                let from = around.iter().map(|s| s.map(|s| s.data.clone())).collect();
                cache.outputs.insert(slices[pos].key, (from, data.clone()));
                out[pos] = Some(data);
            }
            let out: Vec<Slice> = slices
                .iter()
                .zip(out)
                .filter_map(|(s, data)| {
                    Some(Slice {
                        key: s.key,
                        data: data?,
                    })
                })
                .collect();
            // Terms are reused where output slices change, next to the
            // window's ends; of the input slices in between, and of those
            // that changed or left the window, none is kept (their buffers
            // are reused for the next terms). After a time pool the slices
            // start every other tick, on alternate ticks from one tick to
            // the next: the other ticks' terms near the ends are kept too.
            let ends = 2 * k as i64;
            let stride = match &slices[..] {
                [a, b, ..] => b.key - a.key,
                _ => 1,
            };
            let (first, last) = match (slices.first(), slices.last()) {
                (Some(a), Some(b)) => (a.key, b.key),
                _ => (0, -1),
            };
            let index: HashMap<i64, usize> =
                slices.iter().enumerate().map(|(i, s)| (s.key, i)).collect();
            let dropped = cache.terms.extract_if(|&(key, _), (of, _)| {
                let near_an_end = key >= window_start
                    && (key < first + ends * stride || key > last - ends * stride);
                let current = index
                    .get(&key)
                    .is_none_or(|&i| Arc::ptr_eq(of, &slices[i].data));
                !(near_an_end && current)
            });
            let recycled: Vec<Vec<f32>> = dropped
                .filter_map(|(_, (_, term))| Arc::try_unwrap(term).ok())
                .collect();
            cache.spare.extend(recycled);
            // Slices that start before the window can never be used again.
            cache.outputs.retain(|&key, _| key >= window_start);
            slices = if fused.time_pool[li] {
                let pooled = out
                    .chunks_exact(2)
                    .map(|pair| {
                        let key = pair[0].key;
                        let data = match cache.pooled.get(&key) {
                            Some(([a, b], data))
                                if Arc::ptr_eq(a, &pair[0].data)
                                    && Arc::ptr_eq(b, &pair[1].data) =>
                            {
                                data.clone()
                            }
                            _ => {
                                let data: Data = Arc::new(
                                    pair[0]
                                        .data
                                        .iter()
                                        .zip(pair[1].data.iter())
                                        .map(|(a, b)| a.max(*b))
                                        .collect(),
                                );
                                let of = [pair[0].data.clone(), pair[1].data.clone()];
                                cache.pooled.insert(key, (of, data.clone()));
                                data
                            }
                        };
                        Slice { key, data }
                    })
                    .collect();
                cache.pooled.retain(|&key, _| key >= window_start);
                pooled
            } else {
                out
            };
            c_in = c_out;
            hw /= 2;
        }
        // Flatten as [C, T, h, w].
        let t_len = slices.len();
        let plane = hw * hw;
        let mut feats = vec![0.0f32; c_in * t_len * plane];
        for (ti, s) in slices.iter().enumerate() {
            for ch in 0..c_in {
                feats[(ch * t_len + ti) * plane..(ch * t_len + ti + 1) * plane]
                    .copy_from_slice(&s.data[ch * plane..(ch + 1) * plane]);
            }
        }
        let f = c_in * t_len * plane;
        Ok(Tensor::<2>::from_data(
            TensorData::new(feats, [1, f]),
            &device,
        ))
    }
}
