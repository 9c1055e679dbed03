//! average: ensemble average of N consecutive frames (N:1). Integer ADC codes
//! accumulate exactly in i64, whatever N; float samples accumulate in f64.
//! A frame whose geometry differs from the group's (length, sampling, offset,
//! scaling) closes the group early: it is reported with the frames it has and
//! the flag "partial_average".

use super::{FrameError, Stage, Work};
use crate::dsp::average as kernels;
use crate::frame::{Channel, ChannelRole, Samples};

/// Block averaging of `frames` frames.
#[derive(Debug)]
pub struct Average {
    frames: u32,
    group: Option<Group>,
}

#[derive(Debug)]
struct Group {
    first: Work,
    count: u32,
    channels: Vec<Acc>,
}

#[derive(Debug)]
enum Acc {
    Int { sums: Vec<i64>, scale: f64, offset: f64, kind: &'static str },
    Float { sums: Vec<f64> },
}

impl Acc {
    fn new(c: &Channel) -> Acc {
        let n = c.samples.len();
        if c.samples.is_integer() {
            Acc::Int { sums: vec![0; n], scale: c.volts_per_code, offset: c.offset_v, kind: c.samples.kind() }
        } else {
            Acc::Float { sums: vec![0.0; n] }
        }
    }

    fn accepts(&self, c: &Channel) -> bool {
        match self {
            Acc::Int { sums, scale, offset, kind } => {
                c.samples.kind() == *kind && c.volts_per_code == *scale && c.offset_v == *offset && c.samples.len() == sums.len()
            }
            Acc::Float { sums } => !c.samples.is_integer() && c.samples.len() == sums.len(),
        }
    }

    fn add(&mut self, c: &Channel) {
        match (self, &c.samples) {
            (Acc::Int { sums, .. }, Samples::I8(v)) => kernels::add_codes_i8(sums, v),
            (Acc::Int { sums, .. }, Samples::I16(v)) => kernels::add_codes_i16(sums, v),
            (Acc::Int { sums, .. }, Samples::I32(v)) => kernels::add_codes_i32(sums, v),
            (Acc::Float { sums }, Samples::F64(v)) => {
                let (g, o) = (c.volts_per_code, c.offset_v);
                sums.iter_mut().zip(v).for_each(|(s, x)| *s += x * g + o);
            }
            (Acc::Float { sums }, Samples::F32(v)) => {
                let (g, o) = (c.volts_per_code, c.offset_v);
                sums.iter_mut().zip(v).for_each(|(s, &x)| *s += x as f64 * g + o);
            }
            _ => unreachable!("accepts() checked the sample kind"),
        }
    }

    /// Mean in volts: the exact integer sum divided once by the count.
    fn mean_v(&self, count: u32) -> Vec<f64> {
        let n = count as f64;
        match self {
            Acc::Int { sums, scale, offset, .. } => {
                let mut out = vec![0.0; sums.len()];
                kernels::mean_from_sums(sums, count as u64, *scale, *offset, &mut out);
                out
            }
            Acc::Float { sums } => sums.iter().map(|&s| s / n).collect(),
        }
    }
}

impl Average {
    /// Averages `frames` frames per output.
    pub fn new(frames: u32) -> Average {
        Average { frames, group: None }
    }

    fn matches(g: &Group, w: &Work) -> bool {
        let (a, b) = (&g.first.frame, &w.frame);
        a.len() == b.len()
            && a.sample_interval_s == b.sample_interval_s
            // Segments trigger at slightly different sub-sample phases; within one
            // sample they are averaged as they are (start alignment is its own stage).
            && (a.first_sample_offset_s - b.first_sample_offset_s).abs() <= a.sample_interval_s
            && g.first.start.is_some() == w.start.is_some()
            && g.channels[0].accepts(&b.channels[w.stop])
            && w.start.is_none_or(|s| g.channels[1].accepts(&b.channels[s]))
    }

    fn emit(mut g: Group, out: &mut Vec<Work>, partial: bool) {
        let w = &mut g.first;
        let stop_name = w.frame.channels[w.stop].name.clone();
        let mut channels = vec![Channel::from_volts(stop_name, ChannelRole::Stop, g.channels[0].mean_v(g.count))];
        if let Some(s) = w.start {
            let name = w.frame.channels[s].name.clone();
            channels.push(Channel::from_volts(name, ChannelRole::Start, g.channels[1].mean_v(g.count)));
        }
        w.frame.channels = channels;
        w.stop = 0;
        w.start = w.start.map(|_| 1);
        w.frames_averaged = g.count;
        w.lsb_v /= g.count as f64;
        w.report.frames_averaged = g.count;
        w.report.seq_last = w.seq_last;
        if partial {
            w.report.flags.push("partial_average".into());
        }
        out.push(g.first);
    }
}

impl Stage for Average {
    fn name(&self) -> &'static str {
        "average"
    }

    fn process(&mut self, w: Work, out: &mut Vec<Work>) -> Result<(), FrameError> {
        if let Some(g) = self.group.take_if(|g| !Self::matches(g, &w)) {
            Self::emit(g, out, true);
        }
        match &mut self.group {
            Some(g) => {
                g.channels[0].add(&w.frame.channels[w.stop]);
                if let Some(s) = w.start {
                    g.channels[1].add(&w.frame.channels[s]);
                }
                g.count += 1;
                g.first.seq_last = w.seq_last;
                if w.frame.laser_off && !g.first.report.flags.iter().any(|f| f == "laser_off") {
                    g.first.report.flags.push("laser_off_in_group".into());
                }
            }
            None => {
                let mut channels = vec![Acc::new(&w.frame.channels[w.stop])];
                channels[0].add(&w.frame.channels[w.stop]);
                if let Some(s) = w.start {
                    let mut a = Acc::new(&w.frame.channels[s]);
                    a.add(&w.frame.channels[s]);
                    channels.push(a);
                }
                self.group = Some(Group { first: w, count: 1, channels });
            }
        }
        if self.group.as_ref().is_some_and(|g| g.count >= self.frames) {
            Self::emit(self.group.take().expect("checked"), out, false);
        }
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Work>) {
        if let Some(g) = self.group.take() {
            Self::emit(g, out, true);
        }
    }
}
