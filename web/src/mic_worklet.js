// The microphone's AudioWorklet for live sessions over a WebSocket (gt-serve's client page, source "mic"): it turns
// the first input channel into int16 PCM at the context's rate and posts it to the page in chunks of `chunk`
// samples (options.processorOptions.chunk, default 20 ms), each an ArrayBuffer the page sends as one binary message.

class MicPcm extends AudioWorkletProcessor {
  constructor(options) {
    super();
    // `sampleRate` is the AudioWorkletGlobalScope's: the context's rate, declared to the server as mic_rate.
    this.chunk = options?.processorOptions?.chunk ?? Math.round(sampleRate / 50);
    this.pcm = new Int16Array(this.chunk);
    this.filled = 0;
  }

  process(inputs) {
    const samples = inputs[0]?.[0];
    if (samples) {
      for (let i = 0; i < samples.length; i++) {
        const x = Math.max(-1, Math.min(1, samples[i]));
        this.pcm[this.filled++] = x < 0 ? x * 32768 : x * 32767;
        if (this.filled === this.chunk) {
          this.port.postMessage(this.pcm.buffer, [this.pcm.buffer]);
          this.pcm = new Int16Array(this.chunk);
          this.filled = 0;
        }
      }
    }
    return true; // keep running while the input is silent or gone for a moment
  }
}

registerProcessor('gt-mic-pcm', MicPcm);
