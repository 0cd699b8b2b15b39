//! The inputs a network was trained on, and how far a window lies outside
//! them: the out-of-range guard's model side.
//!
//! A model file carries [`InputRanges`], measured on its training split
//! (`fall-guard-lab train` writes them; `fall-guard-lab ranges` adds them to
//! an older file): per joint the smallest and largest angle of every tick a
//! training window can hold, per joint the same for the planned trajectory,
//! and for the camera the range of a frame's mean brightness and of its
//! contrast (pixel standard deviation).
//!
//! Every input the network reads goes through its [`Bounds`]: a joint or
//! plan value outside its range is clipped to it before it is standardised,
//! so an unseen posture cannot turn into tens of standard deviations (a
//! joint that barely moved in training would otherwise do just that), and an
//! [`Excursion`] records which input, its value and its range. A value
//! inside its range is untouched, bit for bit, and so is every training
//! window (the ranges hold all of them). Frames are not clipped (a frame has
//! no per-pixel range); their summary is reported.
//!
//! A file without ranges has no bounds: nothing is clipped and nothing is
//! reported. Bounds derived from the stored standardisation were tried and
//! refused: the simulated joints are heavy-tailed (a head joint with a
//! standard deviation of 0.06 deg reads 5 deg in a fall), so `mean +- 5 sd`
//! flagged 4 of the 4 bundled simulated falls and moved their forecasts by
//! up to 0.93.

use serde::{Deserialize, Serialize};

use super::file::ModelMeta;

/// The range of every input over the training split, stored in the model
/// file's metadata.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InputRanges {
    /// What they were measured on: data set, split, episodes, ticks.
    pub measured_on: String,
    /// Per joint in model order, `[min, max]` of the angle, radians.
    pub joints: Vec<[f32; 2]>,
    /// Per joint, `[min, max]` of the planned trajectory, radians.
    pub plan: Vec<[f32; 2]>,
    /// `[min, max]` of a frame's mean pixel value (all three channels, in
    /// `[0, 1]`); none: measured without frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_mean: Option<[f32; 2]>,
    /// `[min, max]` of a frame's pixel standard deviation.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_std: Option<[f32; 2]>,
}

/// One input the guard watches.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Input {
    /// Joint angle, model order.
    Joint(usize),
    /// The planned trajectory of a joint.
    Plan(usize),
    /// A frame's mean brightness.
    FrameMean,
    /// A frame's contrast (pixel standard deviation).
    FrameStd,
}

/// The bounds a model's inputs are held to.
#[derive(Debug, Clone, PartialEq)]
pub struct Bounds {
    pub joints: Vec<[f32; 2]>,
    pub plan: Vec<[f32; 2]>,
    pub frame_mean: Option<[f32; 2]>,
    pub frame_std: Option<[f32; 2]>,
    /// What the ranges were measured on.
    pub measured_on: String,
}

/// An input outside its bound.
#[derive(Debug, Clone, PartialEq)]
pub struct Excursion {
    pub input: Input,
    /// The value read (radians for joints and plan).
    pub value: f32,
    /// The bound, `[min, max]`.
    pub bound: [f32; 2],
}

impl Excursion {
    /// How far outside its bound the value is (positive), in its unit.
    pub fn beyond(&self) -> f32 {
        (self.bound[0] - self.value).max(self.value - self.bound[1])
    }

    /// `"bust_x 36.2 deg, 31.4 deg above its trained range -4.1..4.8 deg"`.
    pub fn describe(&self, joint_names: &[String]) -> String {
        let side = if self.value > self.bound[1] {
            "above"
        } else {
            "below"
        };
        let name = |j: usize| joint_names.get(j).map_or("?", String::as_str);
        let angle = |what: String| {
            format!(
                "{what} {:.1} deg, {:.1} deg {side} its trained range {:.1}..{:.1} deg",
                self.value.to_degrees(),
                self.beyond().to_degrees(),
                self.bound[0].to_degrees(),
                self.bound[1].to_degrees()
            )
        };
        let unit = |what: &str| {
            format!(
                "{what} {:.3}, {:.3} {side} its trained range {:.3}..{:.3}",
                self.value,
                self.beyond(),
                self.bound[0],
                self.bound[1]
            )
        };
        match self.input {
            Input::Joint(j) => angle(name(j).to_string()),
            Input::Plan(j) => angle(format!("plan of {}", name(j))),
            Input::FrameMean => unit("camera brightness"),
            Input::FrameStd => unit("camera contrast"),
        }
    }
}

impl Bounds {
    /// The bounds of `meta`: its measured ranges (none: no bounds).
    pub fn of(meta: &ModelMeta) -> Option<Bounds> {
        meta.input_ranges.as_ref().map(|r| Bounds {
            joints: r.joints.clone(),
            plan: r.plan.clone(),
            frame_mean: r.frame_mean,
            frame_std: r.frame_std,
            measured_on: r.measured_on.clone(),
        })
    }

    /// `value` of joint channel `j` (`plan`: of the planned trajectory)
    /// held to its bound; an excursion is recorded into `out` (the largest
    /// per input: one entry per input).
    pub fn clip(&self, plan: bool, j: usize, value: f32, out: &mut Vec<Excursion>) -> f32 {
        let table = if plan { &self.plan } else { &self.joints };
        let Some(&[lo, hi]) = table.get(j) else {
            return value;
        };
        if value >= lo && value <= hi {
            return value;
        }
        let input = if plan {
            Input::Plan(j)
        } else {
            Input::Joint(j)
        };
        let e = Excursion {
            input,
            value,
            bound: [lo, hi],
        };
        if e.beyond() > tolerance(lo, hi, ANGLE_TOLERANCE_RAD) {
            record(out, e);
        }
        value.clamp(lo, hi)
    }

    /// A frame (`[3, S, S]` in `[0, 1]`) against the brightness and
    /// contrast bounds; excursions into `out`.
    pub fn check_frame(&self, frame: &[f32], out: &mut Vec<Excursion>) {
        if self.frame_mean.is_none() && self.frame_std.is_none() {
            return;
        }
        let (mean, std) = frame_summary(frame);
        for (input, value, bound) in [
            (Input::FrameMean, mean, self.frame_mean),
            (Input::FrameStd, std, self.frame_std),
        ] {
            if let Some([lo, hi]) = bound {
                let beyond = (lo - value).max(value - hi);
                if beyond > tolerance(lo, hi, FRAME_TOLERANCE) {
                    record(
                        out,
                        Excursion {
                            input,
                            value,
                            bound: [lo, hi],
                        },
                    );
                }
            }
        }
    }
}

/// An excursion is reported once it exceeds this share of its range's
/// width, or the floor below, whichever is larger: a joint 0.4 deg past
/// what a 20 s walk happened to reach is not a posture the network never
/// saw. The value is clipped to the range all the same.
pub const TOLERANCE_SHARE: f32 = 0.1;
/// The floor of an angle's tolerance: 2 deg.
pub const ANGLE_TOLERANCE_RAD: f32 = 2.0 * std::f32::consts::PI / 180.0;
/// The floor of a frame summary's tolerance (values in `[0, 1]`).
pub const FRAME_TOLERANCE: f32 = 0.02;

/// How far past `[lo, hi]` a value may lie before it is reported.
pub fn tolerance(lo: f32, hi: f32, floor: f32) -> f32 {
    (TOLERANCE_SHARE * (hi - lo)).max(floor)
}

/// Keeps the largest excursion per input.
pub fn record(out: &mut Vec<Excursion>, e: Excursion) {
    match out.iter_mut().find(|x| x.input == e.input) {
        Some(x) if x.beyond() < e.beyond() => *x = e,
        Some(_) => {}
        None => out.push(e),
    }
}

/// Mean and standard deviation of a frame's values.
pub fn frame_summary(frame: &[f32]) -> (f32, f32) {
    if frame.is_empty() {
        return (0.0, 0.0);
    }
    let n = frame.len() as f64;
    let mean = frame.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
    let var = frame
        .iter()
        .map(|&v| (f64::from(v) - mean).powi(2))
        .sum::<f64>()
        / n;
    (mean as f32, var.sqrt() as f32)
}

/// Running `[min, max]` of the inputs of training ticks, for
/// `fall-guard-lab ranges`.
#[derive(Debug, Clone)]
pub struct RangeMeter {
    joints: Vec<[f32; 2]>,
    plan: Vec<[f32; 2]>,
    frame_mean: Option<[f32; 2]>,
    frame_std: Option<[f32; 2]>,
}

fn widen(r: &mut [f32; 2], v: f32) {
    if v.is_finite() {
        r[0] = r[0].min(v);
        r[1] = r[1].max(v);
    }
}

impl RangeMeter {
    pub fn new(n_joints: usize) -> RangeMeter {
        let empty = [f32::INFINITY, f32::NEG_INFINITY];
        RangeMeter {
            joints: vec![empty; n_joints],
            plan: vec![empty; n_joints],
            frame_mean: None,
            frame_std: None,
        }
    }

    /// One tick's joint angles (model order).
    pub fn joints(&mut self, joints: &[f32]) {
        for (r, &v) in self.joints.iter_mut().zip(joints) {
            widen(r, v);
        }
    }

    /// Planned rows, `C` values each.
    pub fn plan(&mut self, rows: &[f32]) {
        let c = self.plan.len();
        if c == 0 {
            return;
        }
        for row in rows.chunks_exact(c) {
            for (r, &v) in self.plan.iter_mut().zip(row) {
                widen(r, v);
            }
        }
    }

    /// One frame, `[3, S, S]` in `[0, 1]`.
    pub fn frame(&mut self, frame: &[f32]) {
        let (mean, std) = frame_summary(frame);
        let empty = [f32::INFINITY, f32::NEG_INFINITY];
        widen(self.frame_mean.get_or_insert(empty), mean);
        widen(self.frame_std.get_or_insert(empty), std);
    }

    /// The ranges, or `None` if a joint never had a value.
    pub fn finish(self, measured_on: String) -> Option<InputRanges> {
        let seen = |r: &[f32; 2]| r[0] <= r[1];
        if !self.joints.iter().all(seen) {
            return None;
        }
        // A plan channel never seen (a set without plans) is unbounded
        // (finite: JSON has no infinity).
        let plan = self
            .plan
            .into_iter()
            .map(|r| if seen(&r) { r } else { [f32::MIN, f32::MAX] })
            .collect();
        Some(InputRanges {
            measured_on,
            joints: self.joints,
            plan,
            frame_mean: self.frame_mean.filter(seen),
            frame_std: self.frame_std.filter(seen),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bounds() -> Bounds {
        Bounds {
            joints: vec![[-0.1, 0.1], [0.0, 1.0]],
            plan: vec![[-0.2, 0.2], [0.0, 1.0]],
            frame_mean: Some([0.2, 0.6]),
            frame_std: Some([0.05, 0.3]),
            measured_on: "test".into(),
        }
    }

    #[test]
    fn a_value_inside_is_untouched_and_one_outside_is_clipped_and_named() {
        let b = bounds();
        let mut out = Vec::new();
        for v in [-0.1f32, 0.0, 0.0999, 0.1] {
            assert_eq!(b.clip(false, 0, v, &mut out).to_bits(), v.to_bits());
        }
        assert!(out.is_empty());
        // Past the range by less than its tolerance (2 deg here): clipped,
        // not reported.
        assert_eq!(b.clip(false, 0, 0.13, &mut out), 0.1);
        assert!(out.is_empty());
        assert_eq!(b.clip(false, 0, 0.5, &mut out), 0.1);
        assert_eq!(b.clip(false, 0, 0.3, &mut out), 0.1);
        assert_eq!(b.clip(true, 1, -1.0, &mut out), 0.0);
        assert_eq!(out.len(), 2, "{out:?}");
        assert_eq!(out[0].input, Input::Joint(0));
        assert_eq!(out[0].value, 0.5, "the largest excursion is kept");
        assert!((out[0].beyond() - 0.4).abs() < 1e-6);
        let names = vec!["bust_x".to_string(), "l_knee_y".to_string()];
        let text = out[0].describe(&names);
        assert!(
            text.starts_with("bust_x 28.6 deg, 22.9 deg above"),
            "{text}"
        );
        assert!(out[1]
            .describe(&names)
            .starts_with("plan of l_knee_y -57.3 deg, 57.3 deg below"));
    }

    #[test]
    fn frames_are_judged_by_brightness_and_contrast() {
        let b = bounds();
        let mut out = Vec::new();
        let grey: Vec<f32> = (0..300)
            .map(|i| if i % 2 == 0 { 0.3 } else { 0.5 })
            .collect();
        b.check_frame(&grey, &mut out);
        assert!(out.is_empty(), "{out:?}");
        // Brightness 0.61 against 0.2..0.6: within its tolerance (0.04).
        let bright: Vec<f32> = (0..300)
            .map(|i| if i % 2 == 0 { 0.41 } else { 0.81 })
            .collect();
        b.check_frame(&bright, &mut out);
        assert!(out.is_empty(), "{out:?}");
        b.check_frame(&vec![1.0; 300], &mut out);
        let inputs: Vec<Input> = out.iter().map(|e| e.input).collect();
        assert_eq!(inputs, vec![Input::FrameMean, Input::FrameStd]);
    }

    #[test]
    fn the_meter_measures_minimum_and_maximum() {
        let mut m = RangeMeter::new(2);
        m.joints(&[0.1, -0.5]);
        m.joints(&[-0.3, 0.2]);
        m.joints(&[f32::NAN, 0.0]);
        m.plan(&[0.0, 1.0, 2.0, -1.0]);
        m.frame(&[0.0, 1.0]);
        let r = m.finish("test".into()).expect("every joint seen");
        assert_eq!(r.joints, vec![[-0.3, 0.1], [-0.5, 0.2]]);
        assert_eq!(r.plan, vec![[0.0, 2.0], [-1.0, 1.0]]);
        assert_eq!(r.frame_mean, Some([0.5, 0.5]));
        assert_eq!(r.frame_std, Some([0.5, 0.5]));
        assert!(RangeMeter::new(1).finish("none".into()).is_none());
    }
}
