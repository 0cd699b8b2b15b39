//! The EMP network: encoders switched by the ablation, the classifier, and
//! the monotone multi-horizon output.
//!
//! In: an [`EmpInput`] batch (standardised joints and plan, low-passed frames).
//! Out: logits `[B, K]` with `z_1 = a_1`, `z_k = z_{k-1} + softplus(a_k)`, so
//! the probabilities `sigmoid(z)` are non-decreasing in the horizon.
//! [`Emp`] trains; [`EmpInference`] is the same network with fused kernels and
//! no autodiff.

use burn::nn::{Dropout, DropoutConfig, Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::activation::{gelu, softplus};

use super::config::{Ablation, ModelConfig};
use super::host_linear::HostLinear;
use super::motion::{MotionEncoder, MotionHost};
use super::plan::{PlanEncoder, PlanFused};
use super::vision::{VisionEncoder, VisionFused};

/// One batch of network inputs. Tensors the ablation does not use may be `None`.
#[derive(Debug, Clone)]
pub struct EmpInput {
    /// Standardised joint angles `[B, N, C]`.
    pub joints: Tensor<3>,
    /// Standardised plan `[B, N + h_K, C]`.
    pub plan: Option<Tensor<3>>,
    /// Low-passed frames `[B, 3, N, 2a, 2a]`.
    pub frames: Option<Tensor<5>>,
}

/// Concatenated features -> `d_model` -> GELU -> dropout -> `K`.
#[derive(Module, Debug)]
pub struct Classifier {
    hidden: Linear,
    dropout: Dropout,
    out: Linear,
}

impl Classifier {
    fn new(in_features: usize, cfg: &ModelConfig, device: &Device) -> Self {
        Classifier {
            hidden: LinearConfig::new(in_features, cfg.d_model).init(device),
            dropout: DropoutConfig::new(cfg.dropout).init(),
            out: LinearConfig::new(cfg.d_model, cfg.k()).init(device),
        }
    }

    /// `[B, F]` -> monotone logits `[B, K]`.
    pub fn forward(&self, features: Tensor<2>) -> Tensor<2> {
        let a = self
            .out
            .forward(self.dropout.forward(gelu(self.hidden.forward(features))));
        monotone_logits(a)
    }
}

/// `z_1 = a_1`, `z_k = z_{k-1} + softplus(a_k)`.
pub fn monotone_logits(a: Tensor<2>) -> Tensor<2> {
    let [b, k] = a.dims();
    if k == 1 {
        return a;
    }
    let first = a.clone().slice([0..b, 0..1]);
    let rest = softplus(a.slice([0..b, 1..k]), 1.0);
    Tensor::cat(vec![first, rest], 1).cumsum(1)
}

/// The trainable network.
#[derive(Module, Debug)]
pub struct Emp {
    /// Proprioception (always on).
    pub motion: MotionEncoder,
    /// Motion plan (MP, EMP).
    pub plan: Option<PlanEncoder>,
    /// Egocentric vision (EP, EMP).
    pub vision: Option<VisionEncoder>,
    /// Classifier head.
    pub classifier: Classifier,
}

impl Emp {
    /// A freshly initialised network for `ablation`.
    pub fn new(cfg: &ModelConfig, ablation: Ablation, device: &Device) -> Self {
        let mut features = MotionEncoder::out_features(cfg);
        let plan = ablation.uses_plan().then(|| {
            features += PlanEncoder::out_features(cfg);
            PlanEncoder::new(cfg, device)
        });
        let vision = ablation.uses_vision().then(|| {
            features += VisionEncoder::out_features(cfg);
            VisionEncoder::new(cfg, device)
        });
        Emp {
            motion: MotionEncoder::new(cfg, device),
            plan,
            vision,
            classifier: Classifier::new(features, cfg, device),
        }
    }

    /// Monotone logits `[B, K]`. Panics only on a programming error (a used input missing).
    pub fn forward(&self, input: EmpInput) -> Tensor<2> {
        let mut feats = vec![self.motion.forward(input.joints)];
        if let Some(p) = &self.plan {
            feats.push(p.forward(input.plan.expect("plan input for a plan ablation"), None));
        }
        if let Some(v) = &self.vision {
            feats.push(v.forward(input.frames.expect("frames input for a vision ablation")));
        }
        self.classifier.forward(Tensor::cat(feats, 1))
    }

    /// The inference form: no autodiff, fused kernels, the classifier's
    /// input projection on the host at the weights' own precision
    /// ([`HostLinear`]). The unfused vision weights are not kept.
    pub fn to_inference(&self) -> EmpInference {
        let Emp {
            motion,
            plan,
            vision,
            classifier,
        } = self.valid();
        EmpInference {
            plan_fused: plan.as_ref().map(PlanEncoder::fuse),
            vision_fused: vision.as_ref().map(VisionEncoder::fuse),
            motion: MotionHost::of(&motion),
            plan,
            hidden: HostLinear::from_linear(&classifier.hidden),
            out: classifier.out,
        }
    }
}

/// The network for inference: fused Inception kernels, no autodiff, no dropout.
#[derive(Debug, Clone)]
pub struct EmpInference {
    /// The motion encoder on the host ([`MotionHost`]).
    motion: MotionHost,
    /// Embedding, norms and period choice (its convolutions run fused).
    plan: Option<PlanEncoder>,
    /// Classifier input projection `features -> d_model`.
    hidden: HostLinear,
    /// Classifier output `d_model -> K`.
    out: Linear,
    /// Fused trajectory convolutions.
    pub plan_fused: Option<PlanFused>,
    /// Fused vision convolutions.
    pub vision_fused: Option<VisionFused>,
}

impl EmpInference {
    /// Whole-window forward: monotone logits `[B, K]`.
    pub fn forward(&self, input: EmpInput) -> Tensor<2> {
        let vision = match (&self.vision_fused, input.frames.clone()) {
            (Some(v), Some(f)) => Some(v.forward(f)),
            _ => None,
        };
        self.forward_with_vision(input, vision)
    }

    /// Forward with the vision features already computed.
    pub fn forward_with_vision(
        &self,
        input: EmpInput,
        vision_features: Option<Tensor<2>>,
    ) -> Tensor<2> {
        let plan = input.plan.and_then(|p| self.plan_features(p));
        self.forward_with_features(input.joints, plan, vision_features)
    }

    /// The trajectory encoder's features `[B, L·d_t]` of a standardised
    /// plan window `[B, L, C]`; `None` for a network without a plan input.
    pub fn plan_features(&self, plan: Tensor<3>) -> Option<Tensor<2>> {
        self.plan
            .as_ref()
            .map(|p| p.forward(plan, self.plan_fused.as_ref()))
    }

    /// Forward with the trajectory and vision features already computed
    /// (the streaming path): motion, the classifier.
    pub fn forward_with_features(
        &self,
        joints: Tensor<3>,
        plan_features: Option<Tensor<2>>,
        vision_features: Option<Tensor<2>>,
    ) -> Tensor<2> {
        let mut feats = vec![self.motion.forward(joints)];
        if self.plan.is_some() {
            if let Some(p) = plan_features {
                feats.push(p);
            }
        }
        if self.vision_fused.is_some() {
            if let Some(v) = vision_features {
                feats.push(v);
            }
        }
        let h = self.hidden.forward(Tensor::cat(feats, 1));
        monotone_logits(self.out.forward(gelu(h)))
    }

    /// Holds the classifier's input projection in int8
    /// ([`HostLinear::to_int8`]).
    pub fn quantize_projection(&mut self) {
        self.hidden = self.hidden.to_int8();
    }

    /// Runs the trajectory encoder's convolutions in integers
    /// ([`HostConv::to_int8`](super::host_conv::HostConv::to_int8)). The
    /// vision encoder's stay f32: there each im2col value meets only 8-32
    /// output channels, and quantising it costs about what the integer
    /// products save (`docs/performance.md`).
    pub fn quantize_convolutions(&mut self) {
        if let Some(plan) = &mut self.plan_fused {
            plan.to_int8();
        }
    }

    /// Bytes the classifier's input projection takes (f16 when the file was).
    pub fn projection_bytes(&self) -> usize {
        self.hidden.bytes()
    }
}
