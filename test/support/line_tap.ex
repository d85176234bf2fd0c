defmodule Vws.Test.LineTap do
  @moduledoc """
  A DDCMP line between the CEC and a VAL II, with faults placed exactly where a test wants them.

  It listens on `listen` (default a free local TCP port; `endpoint/1`), and for the connection
  it accepts dials `upstream` (the controller), then relays every DDCMP message both ways: it
  decodes each direction with `Vws.Links.DDCMP.Frame` and forwards each message re-encoded (the same
  bytes the sender sent). A fault rule (`fault/4`) acts once, on the first message in its
  direction (`:to_val` or `:to_cec`) that its predicate accepts: `:drop` loses the message,
  `:corrupt` changes one byte of its last block check (a data message then fails
  its data CRC, a control message its header CRC). `log/1` lists every message seen, `{direction, frame, fate}`, in order.

  Predicates get `{frame, val_message | nil}`, the VAL message decoded from a data message's
  bytes, and the tap's memory of the other direction, so a rule can say "the ACK of the data
  message that carried this REPLY" (see `acks_val?/2`).
  """
  use GenServer

  alias Vws.Links.DDCMP.Frame
  alias Vws.Links.Transport

  def start_link(opts), do: GenServer.start_link(__MODULE__, opts)

  @doc "The endpoint the CEC should dial."
  def endpoint(tap), do: GenServer.call(tap, :endpoint)

  @doc "Adds a one-shot fault rule; `fun.(frame, val_message, seen)` selects the message."
  def fault(tap, direction, fun, action) when action in [:drop, :corrupt],
    do: GenServer.call(tap, {:fault, direction, fun, action})

  @doc "Every message relayed so far: `[{direction, frame, :passed | :dropped | :corrupted}]`."
  def log(tap), do: GenServer.call(tap, :log)

  @doc "Rules that have not fired yet."
  def pending(tap), do: GenServer.call(tap, :pending)

  @doc """
  A predicate for a `:to_cec` rule: an ACK acknowledging the data message (sent to the VAL) whose
  VAL message `val_fun` accepts.
  """
  def acks_val?(val_fun) do
    fn frame, _val, seen ->
      match?(%Frame.Control{type: :ack}, frame) and
        Enum.any?(seen.to_val, fn {num, m} -> val_fun.(m) and frame.rcvr == num end)
    end
  end

  @impl true
  def init(opts) do
    {:ok, listener} = Transport.listen(Keyword.get(opts, :listen, "tcp://127.0.0.1:0"))
    owner = self()

    spawn_link(fn ->
      {:ok, conn} = Transport.accept(listener, :infinity)
      :ok = Transport.controlling_process(conn, owner)
      send(owner, {:accepted, conn})
    end)

    {:ok,
     %{
       listener: listener,
       upstream: Keyword.fetch!(opts, :upstream),
       cec: nil,
       val: nil,
       decoders: %{to_val: Frame.new(), to_cec: Frame.new()},
       rules: [],
       log: [],
       seen: %{to_val: [], to_cec: []}
     }}
  end

  @impl true
  def handle_call(:endpoint, _from, s),
    do: {:reply, to_string(Transport.listener_endpoint(s.listener)), s}

  def handle_call({:fault, direction, fun, action}, _from, s),
    do: {:reply, :ok, %{s | rules: s.rules ++ [{direction, fun, action}]}}

  def handle_call(:log, _from, s), do: {:reply, Enum.reverse(s.log), s}
  def handle_call(:pending, _from, s), do: {:reply, length(s.rules), s}

  @impl true
  def handle_info({:accepted, cec}, s) do
    {:ok, val} = Transport.connect(s.upstream)
    :ok = Transport.activate(cec)
    :ok = Transport.activate(val)
    {:noreply, %{s | cec: cec, val: val}}
  end

  def handle_info(msg, s) do
    cond do
      s.cec && Transport.handle_message(s.cec, msg) != :unknown ->
        relay(Transport.handle_message(s.cec, msg), :to_val, s)

      s.val && Transport.handle_message(s.val, msg) != :unknown ->
        relay(Transport.handle_message(s.val, msg), :to_cec, s)

      true ->
        {:noreply, s}
    end
  end

  defp relay({:data, bytes}, direction, s) do
    {from, to} = if direction == :to_val, do: {s.cec, s.val}, else: {s.val, s.cec}
    {frames, decoder} = Frame.feed(s.decoders[direction], bytes)
    s = put_in(s.decoders[direction], decoder)
    s = Enum.reduce(frames, s, &forward(&1, direction, to, &2))
    Transport.activate(from)
    {:noreply, s}
  end

  defp relay(_closed_or_error, _direction, s) do
    if s.cec, do: Transport.close(s.cec)
    if s.val, do: Transport.close(s.val)
    {:noreply, %{s | cec: nil, val: nil}}
  end

  defp forward({:error, _} = error, direction, _to, s) do
    %{s | log: [{direction, error, :passed} | s.log]}
  end

  defp forward(frame, direction, to, s) do
    val = val_message(frame)

    s =
      case {frame, val} do
        {%Frame.Data{num: num}, %{} = m} -> update_in(s.seen[direction], &[{num, m} | &1])
        _ -> s
      end

    {action, s} = take_rule(s, direction, frame, val)
    bytes = IO.iodata_to_binary(Frame.encode(frame))

    case action do
      nil ->
        Transport.send(to, bytes)
        %{s | log: [{direction, frame, :passed} | s.log]}

      :drop ->
        %{s | log: [{direction, frame, :dropped} | s.log]}

      :corrupt ->
        # the last byte before the DEL fill: a data CRC byte, or a control message's CRC
        at = byte_size(bytes) - 3
        <<pre::binary-size(at), b, post::binary>> = bytes
        Transport.send(to, <<pre::binary, Bitwise.bxor(b, 0x5A), post::binary>>)
        %{s | log: [{direction, frame, :corrupted} | s.log]}
    end
  end

  defp take_rule(s, direction, frame, val) do
    case Enum.split_while(s.rules, fn {d, fun, _} ->
           not (d == direction and fun.(frame, val, s.seen))
         end) do
      {_, []} -> {nil, s}
      {before, [{_, _, action} | rest]} -> {action, %{s | rules: before ++ rest}}
    end
  end

  defp val_message(%Frame.Data{data: data}) do
    case Vws.Links.VAL.Message.decode(data) do
      {:ok, m} -> m
      _ -> nil
    end
  end

  defp val_message(_), do: nil
end
