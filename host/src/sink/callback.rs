//! Sinks for a program that embeds loglio: a closure called with each event, or a channel.

use std::sync::mpsc::{Receiver, SyncSender, sync_channel};

use super::{Sink, SinkError, SinkEvent, Wants};

/// Calls a closure with each event on the sink's thread.
pub struct CallbackSink<F> {
    name: String,
    wants: Wants,
    f: F,
}

impl<F> std::fmt::Debug for CallbackSink<F> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CallbackSink").field("name", &self.name).finish_non_exhaustive()
    }
}

impl<F: FnMut(&SinkEvent) + Send> CallbackSink<F> {
    /// A sink named `name` wanting `wants`, calling `f`.
    pub fn new(name: impl Into<String>, wants: Wants, f: F) -> Self {
        CallbackSink { name: name.into(), wants, f }
    }
}

impl<F: FnMut(&SinkEvent) + Send> Sink for CallbackSink<F> {
    fn name(&self) -> String {
        self.name.clone()
    }
    fn wants(&self) -> Wants {
        self.wants
    }
    fn handle(&mut self, ev: &SinkEvent) -> Result<(), SinkError> {
        (self.f)(ev);
        Ok(())
    }
}

/// Sends each event into a bounded channel; the receiver is the embedding program's. A
/// receiver that stops reading fills the channel, then the sink's queue, and events are
/// dropped and counted: the odometry goes on. A receiver that is dropped makes each send an
/// error (counted, said once).
#[derive(Debug)]
pub struct ChannelSink {
    wants: Wants,
    tx: SyncSender<SinkEvent>,
}

impl ChannelSink {
    /// A sink and the receiver of its events (`capacity` events in the channel).
    pub fn new(wants: Wants, capacity: usize) -> (ChannelSink, Receiver<SinkEvent>) {
        let (tx, rx) = sync_channel(capacity);
        (ChannelSink { wants, tx }, rx)
    }
}

impl Sink for ChannelSink {
    fn name(&self) -> String {
        "channel".into()
    }
    fn wants(&self) -> Wants {
        self.wants
    }
    fn handle(&mut self, ev: &SinkEvent) -> Result<(), SinkError> {
        self.tx.send(ev.clone()).map_err(|_| SinkError("the receiver is gone".into()))
    }
}
