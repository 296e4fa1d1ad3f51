//! Weight averaging: one network whose every parameter is the weighted mean of the same
//! parameter in several networks of one shape (`minflow average`).
//!
//! Stochastic weight averaging (Izmailov et al. 2018, "Averaging Weights Leads to Wider
//! Optima and Better Generalization", eq. 1: the running mean of the weights an SGD
//! trajectory visits) and its uniform "model soup" form (Wortsman et al. 2022, "Model soups",
//! sec. 2): weights of one run, taken some epochs apart, averaged after training. Each
//! parameter is averaged element by element in `f64` on the host; the modules are walked in
//! burn's visiting order, which is the same for networks of one configuration.

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};

/// Why networks could not be averaged.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AverageError {
    /// No network, or weights that do not fit: another count than the networks', a
    /// negative or non-finite weight, or a sum that is 0 or not finite.
    #[error("{0}")]
    Input(String),
    /// Network `index` (0-based) has other parameters than the first.
    #[error("network {index} differs from the first: {what}")]
    Shape {
        /// The network's position in the list.
        index: usize,
        /// What differs.
        what: String,
    },
}

/// The parameters of a network as flat `f32` vectors with their shapes, in visiting order.
#[derive(Default)]
struct Collect {
    params: Vec<(Vec<usize>, Vec<f32>)>,
}

impl<B: Backend> ModuleVisitor<B> for Collect {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        let tensor = param.val();
        let shape = tensor.dims().to_vec();
        let values = tensor.into_data().convert::<f32>().into_vec::<f32>();
        self.params
            .push((shape, values.expect("an f32 tensor converts to a Vec<f32>")));
    }
}

/// Writes the averaged values back, parameter by parameter, in visiting order.
struct Replace {
    means: std::vec::IntoIter<(Vec<usize>, Vec<f32>)>,
}

impl<B: Backend> ModuleMapper<B> for Replace {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<B, D>>) -> Param<Tensor<B, D>> {
        let (shape, mean) = self.means.next().expect("one mean a parameter");
        let (id, tensor, mapper) = param.consume();
        let (device, grad) = (tensor.device(), tensor.is_require_grad());
        let tensor = Tensor::<B, D>::from_data(TensorData::new(mean, shape), &device);
        // A trainable parameter stays trainable (on an autodiff backend).
        let tensor = if grad { tensor.require_grad() } else { tensor };
        Param::from_mapped_value(id, tensor, mapper)
    }
}

/// The network whose parameters are `sum_k weights[k] * nets[k]` over the networks, the
/// weights normalised to sum to 1 (`None`: all equal). The first network gives the
/// structure, the parameter ids and the device of the result.
///
/// # Errors
/// [`AverageError::Input`] for weights that do not fit the networks ([`normalised`]);
/// [`AverageError::Shape`] when a network's parameters differ from the first's in number
/// or shape.
pub fn average<B: Backend, M: Module<B>>(
    nets: Vec<M>,
    weights: Option<&[f64]>,
) -> Result<M, AverageError> {
    let weights = normalised(nets.len(), weights)?;
    let mut collected = nets.iter().map(|net| {
        let mut c = Collect::default();
        net.visit(&mut c);
        c.params
    });
    let first = collected
        .next()
        .expect("checked above: at least one network");
    let mut sums: Vec<Vec<f64>> = (first.iter())
        .map(|(_, v)| v.iter().map(|&x| weights[0] * f64::from(x)).collect())
        .collect();
    for (index, params) in collected.enumerate().map(|(i, p)| (i + 1, p)) {
        if params.len() != first.len() {
            let what = format!("{} parameters against {}", params.len(), first.len());
            return Err(AverageError::Shape { index, what });
        }
        for (p, ((shape, values), sum)) in params.iter().zip(sums.iter_mut()).enumerate() {
            if *shape != first[p].0 {
                let what = format!("parameter {p} has shape {shape:?} against {:?}", first[p].0);
                return Err(AverageError::Shape { index, what });
            }
            for (s, &x) in sum.iter_mut().zip(values) {
                *s += weights[index] * f64::from(x);
            }
        }
    }
    let means: Vec<(Vec<usize>, Vec<f32>)> = (first.into_iter().zip(sums))
        .map(|((shape, _), sum)| (shape, sum.into_iter().map(|s| s as f32).collect()))
        .collect();
    let net = nets
        .into_iter()
        .next()
        .expect("checked above: at least one network");
    Ok(net.map(&mut Replace {
        means: means.into_iter(),
    }))
}

/// `weights` (or `n` equal ones) scaled to sum to 1, as [`average`] uses them.
///
/// # Errors
/// [`AverageError::Input`] for `n` = 0, another count than `n`, a negative or non-finite
/// weight, or a sum that is 0 or not finite.
pub fn normalised(n: usize, weights: Option<&[f64]>) -> Result<Vec<f64>, AverageError> {
    if n == 0 {
        return Err(AverageError::Input("no network to average".into()));
    }
    let weights = match weights {
        None => vec![1.0; n],
        Some(w) if w.len() == n => w.to_vec(),
        Some(w) => {
            let msg = format!("{} weights for {n} networks", w.len());
            return Err(AverageError::Input(msg));
        }
    };
    let total: f64 = weights.iter().sum();
    if weights.iter().any(|w| !w.is_finite() || *w < 0.0) || !(total > 0.0 && total.is_finite()) {
        let msg = format!("weights must be finite, >= 0 and of a positive sum, got {weights:?}");
        return Err(AverageError::Input(msg));
    }
    Ok(weights.into_iter().map(|w| w / total).collect())
}
